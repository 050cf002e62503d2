"""``bayesdrive criticize``: what the base model gets wrong on a data set, and which extension fixes it."""

from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from bayesdrive.cli.common import (
    ForceResults,
    check_cluster_options,
    check_json_out,
    console,
    emit_json,
    err_console,
    fail,
    results_command,
    results_folder,
)

__all__ = ["criticize_command", "print_report"]


@results_command
def criticize_command(
    data: Annotated[str, typer.Argument(help="A data file or folder, or a data set name.")],
    format: Annotated[
        str | None, typer.Option("--format", "-f", help="Reader format (detected if omitted).")
    ] = None,
    model: Annotated[str, typer.Option("--model", help="Base driver model.")] = "idm",
    seed: Annotated[int, typer.Option("--seed", help="Seed of every random draw.")] = 0,
    particles: Annotated[
        int | None,
        typer.Option(
            "--particles", help="Particles per vehicle and model (default: the sampler's, 128)."
        ),
    ] = None,
    unmoved_tolerance: Annotated[
        float | None,
        typer.Option(
            "--unmoved-tolerance",
            help="Move each tempering stage until a particle stays put with at most this "
            "probability (0: a fixed number of moves; default: the sampler's, 0.01).",
        ),
    ] = None,
    driver: Annotated[
        str | None,
        typer.Option("--driver", help="Only vehicles with this driver (human, acc, unknown)."),
    ] = None,
    vehicles: Annotated[
        int | None,
        typer.Option(
            "--vehicles",
            help="Only the first N vehicles with scored steps, counted as `fit --vehicles` does.",
        ),
    ] = None,
    rollouts: Annotated[
        int,
        typer.Option(
            "--rollouts",
            help="Rollouts per held-out window (0: skip them; then nothing is adopted).",
        ),
    ] = 32,
    causes: Annotated[
        str | None,
        typer.Option(
            "--causes",
            help="Comma-separated causes (default: all but state_correction, screened on request).",
        ),
    ] = None,
    max_rounds: Annotated[
        int,
        typer.Option(
            "--max-rounds",
            help="Rounds of extending the model by the cause adopted (named, with --rollouts 0) "
            "and looking for the next (1: the first cause only).",
        ),
    ] = 3,
    final_particles: Annotated[
        int,
        typer.Option(
            "--final-particles",
            help="smc particles of the final model's fit written by --out (final_model.nc).",
        ),
    ] = 1000,
    out: Annotated[
        Path | None, typer.Option("--out", help="Folder for the check pictures.")
    ] = None,
    json_out: Annotated[
        str | None, typer.Option("--json", help="Write the report as JSON (- = stdout).")
    ] = None,
    force: ForceResults = False,
    cluster: Annotated[
        str | None,
        typer.Option(
            "--cluster",
            help="Fit chunks of vehicles on Dask: local[:N] starts N single-threaded process "
            "workers (default: one per core), tcp://HOST:PORT uses a running scheduler. Same "
            "result as without.",
        ),
    ] = None,
    chunk_size: Annotated[
        int | None,
        typer.Option(
            "--chunk-size",
            min=1,
            help="With --cluster: vehicles per task (default: as fit --cluster's).",
        ),
    ] = None,
) -> None:
    """Fit the model, check it, name the cause of its misfit, adopt it if it simulates better.

    The extensions fitted are those the checks point to."""
    # Imported here so `bayesdrive --help` stays fast (JAX is heavy to import).
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from bayesdrive.criticism.criticize import CriticizeConfig, criticize
    from bayesdrive.data.errors import DataError
    from bayesdrive.drivers.extensions import CAUSES, DEFAULT_CAUSES, extend
    from bayesdrive.drivers.registry import get_model
    from bayesdrive.inference.core.likelihood import check_model

    check_json_out(json_out, force)
    check_cluster_options(cluster, chunk_size)
    results = None if out is None else results_folder(out, "criticize", force=force)
    try:
        traj = _load(data, format)
    except (DataError, FileNotFoundError) as error:
        raise fail(str(error)) from None
    try:
        base = get_model(model)
    except KeyError as error:
        raise fail(str(error.args[0])) from None
    try:
        check_model(base, "criticize")  # the criticism's samplers score exactly observed states
        reads_car_following(base)
    except (NotImplementedError, TypeError) as error:
        raise fail(f"criticize fits car-following data; model {model!r}: {error}") from None
    chosen = tuple(c.strip() for c in causes.split(",")) if causes else DEFAULT_CAUSES
    unknown = [c for c in chosen if c not in CAUSES]
    if unknown:
        raise fail(f"unknown cause(s) {unknown}; known: {', '.join(CAUSES)}")
    # Built before any work: an extension may need a parameter the base lacks (a drifting time
    # gap needs the IDM's tau). Named causes must all fit; of the default list, those that
    # cannot are left out and said so.
    misfits = {}
    for cause in chosen:
        try:
            extend(cause, base)
        except (KeyError, ValueError) as error:
            misfits[cause] = error.args[0]
    if misfits and causes:
        raise fail(f"cause(s) that cannot extend model {model!r}: {misfits}")
    if misfits:
        err_console.print(f"causes left out, they cannot extend {model!r}: {misfits}")
        chosen = tuple(c for c in chosen if c not in misfits)
    if driver is not None:
        # Followers of that driver type, and every vehicle ahead of them (their inputs).
        tracks = traj.tracks
        chosen_ids = set(tracks.loc[tracks["driver"] == driver, "vehicle_id"])
        if not chosen_ids:
            raise fail(f"no vehicle with driver {driver!r} in {data}")
        leaders = set(tracks.loc[tracks["vehicle_id"].isin(chosen_ids), "leader_id"].dropna())
        second = set(tracks.loc[tracks["vehicle_id"].isin(leaders), "leader_id"].dropna())
        traj = traj.subset(chosen_ids | leaders | second)
    config = CriticizeConfig(num_rollouts=rollouts, causes=chosen, max_rounds=max_rounds)
    if particles is not None:
        config = config._replace(num_particles=particles)
    if unmoved_tolerance is not None:
        config = config._replace(unmoved_tolerance=unmoved_tolerance)
    if (
        config.num_particles < 2
        or rollouts < 0
        or max_rounds < 1
        or final_particles < 2
        or not 0 <= config.unmoved_tolerance < 1
    ):
        raise fail(
            "need --particles >= 2, --rollouts >= 0, --max-rounds >= 1 and 0 <= "
            f"--unmoved-tolerance < 1, got {config.num_particles}, {rollouts}, {max_rounds}, "
            f"{config.unmoved_tolerance}"
        )

    quiet = json_out == "-"
    with ExitStack() as stack:
        client = None
        if cluster is not None:
            from bayesdrive.inference.distributed import open_cluster

            client = stack.enter_context(open_cluster(cluster))
        with Progress(
            SpinnerColumn(),
            TextColumn("{task.description}"),
            TimeElapsedColumn(),
            console=err_console,
            disable=quiet,
            transient=True,
        ) as bar:
            task = bar.add_task("reading", total=None)
            try:
                result = criticize(
                    traj,
                    seed=seed,
                    model=base,
                    config=config,
                    max_vehicles=vehicles,
                    progress=lambda message: bar.update(task, description=message),
                    client=client,
                    chunk_size=chunk_size,
                )
            except (DataError, ValueError) as error:
                raise fail(str(error)) from None
        if results is not None:
            from bayesdrive.reports.criticism_plots import plot_criticism

            written = plot_criticism(result, results.path)
            written += _write_final_model(
                result, traj, seed, results.path, final_particles, client, chunk_size
            )
            results.commit()
            result.report["figures"] = [str(out / p.relative_to(results.path)) for p in written]
    if emit_json(result.report, json_out):
        return
    print_report(result.report)


def _write_final_model(
    result, traj, seed: int, folder: Path, num_particles: int, client, chunk_size: int | None
) -> list[Path]:
    """The final model fitted by smc (its defaults) to the criticized vehicles' fitting windows,
    as a result file ``final_model.nc`` beside its model card ``final_model.md``; with a Dask
    ``client``, in chunks on its cluster (the same result)."""
    import jax

    from bayesdrive.criticism.criticize import named_key
    from bayesdrive.data.atomic import write_text_atomic
    from bayesdrive.drivers.registry import get_model
    from bayesdrive.inference.core.output import save_result
    from bayesdrive.inference.fit import fit
    from bayesdrive.reports.model_card import model_card

    report = result.report
    model = get_model(report["model"])
    err_console.print(f"fitting the final model {model.name} with smc for final_model.nc")
    options = {
        "model": model,
        "engine": "smc",
        "num_particles": num_particles,
        "window": "fit",
        "seed": seed,
        "vehicle_ids": list(result.series.vehicle_ids),
    }
    key = named_key(jax.random.key(seed), "final_model")
    if client is None:
        tree = fit(key, traj, **options)
    else:
        from bayesdrive.inference.distributed import (
            DEFAULT_CHUNK_SIZE,
            fit_on_cluster,
            remove_chunks,
        )

        tree = fit_on_cluster(
            client, key, traj, folder=folder, chunk_size=chunk_size or DEFAULT_CHUNK_SIZE, **options
        )
        remove_chunks(folder)
    path = save_result(tree, folder / "final_model.nc")
    gains = []
    for r in report["rounds"]:
        # The cause that extended the model: the adopted one, or the named one where adoption
        # was not judged.
        cause = r["adopted_cause"] or (r["named"] if r["adopted"] is None else None)
        gain = next((c["gain"] for c in r["causes"] if c["name"] == cause), None)
        if gain is not None and gain["elpd"] is not None:
            gains.append(
                f"round {r['round']}: {r['model']} + {cause}, held-out gain "
                f"{gain['elpd']:.1f} +- {gain['se']:.1f} nats (p = {gain['p_value']:.2g}); "
                f"{r['adoption']}"
            )
    card = model_card(
        tree,
        title=f"{model.name}: the final model of `bayesdrive criticize`",
        description=f"base model {report['base_model']} extended by the causes criticize "
        "found, in rounds",
        label=f"{report['data']['vehicles']} criticized vehicles",
        lines=[
            f"criticism: seed {seed}, verdict {report['verdict']}, rounds "
            f"{len(report['rounds'])} (settings in the criticism's JSON)",
            *(gains or ["no cause was adopted: the final model is the base model"]),
        ],
    )
    card_path = folder / "final_model.md"
    write_text_atomic(card_path, card)
    return [path, card_path]


def reads_car_following(model) -> None:
    """Trace ``model``'s rule on car-following inputs; a TypeError if it needs others (a merge)."""
    import jax
    import jax.numpy as jnp

    from bayesdrive.drivers.base import CarFollowingInputs, EgoState

    zero = jnp.zeros(())
    jax.eval_shape(
        model.mean_acceleration,
        model.defaults(),
        EgoState(zero, zero),
        CarFollowingInputs(zero, zero, zero, zero),
    )


def _load(data: str, format: str | None):
    """A path is read with the readers; anything else is looked up as a data-set name."""
    from bayesdrive.data.readers import read
    from bayesdrive.data.registry import load

    if Path(data).exists():
        return read(data, format=format)
    return load(data, format=format)


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def _yes_no(significant: bool | None) -> str:
    return {True: "[green]yes[/green]", False: "no"}.get(significant, "-")


def print_report(report: dict[str, Any]) -> None:
    """The human-readable criticism: checks, candidate causes with their gains, the verdict."""
    data = report["data"]
    console.rule("[bold]Model criticism")
    console.print(
        f"{data['source']} ({data['format']}): {data['vehicles']} vehicles, "
        f"{data['scored_steps_fit']} fitting and {data['scored_steps_heldout']} held-out steps; "
        f"base model {report['base_model']}, seed {report['seed']}"
    )
    checks = Table(title="Checks on held-out windows (base model)")
    for column in ("check", "number", "p", "points to"):
        checks.add_column(column)
    for check in report["checks"]:
        checks.add_row(
            check["title"],
            _fmt(check["statistic"]),
            _fmt(check["p_value"]),
            ", ".join(check["points_to"]),
        )
    console.print(checks)

    for found in report["rounds"]:
        causes = Table(
            title=f"Round {found['round']}: what extends {found['model']} "
            "(ordered by held-out gain)"
        )
        for column in (
            "cause",
            "screened",
            "elpd gain",
            "se",
            "p",
            "significant",
            "energy score gain",
            "se",
            "p",
            "better",
            "mean RMSE change (m)",
            "collisions",
        ):
            causes.add_column(column)
        for cause in found["causes"]:
            gain = cause["gain"] or {}
            scored = cause.get("forecast") or {}
            causes.add_row(
                cause["name"],
                "yes" if cause["screened_in"] else "no",
                _fmt(gain.get("elpd"), 4),
                _fmt(gain.get("se")),
                _fmt(gain.get("p_value")),
                _yes_no(gain.get("significant")),
                _fmt(scored.get("energy_score_gain")),
                _fmt(scored.get("energy_score_gain_se")),
                _fmt(scored.get("p_value")),
                _yes_no(scored.get("significant")),
                _fmt(scored.get("rmse_mean_position_change_m")),
                _fmt(scored.get("collisions")),
            )
        console.print(causes)
        misfit = ", ".join(m["check"] for m in found.get("misfit", [])) or "none found"
        console.print(
            escape(
                f"Round {found['round']}: misfit {misfit}; verdict {found['verdict']}; "
                f"{found.get('adoption', '')}; {found.get('outcome', '')}"
            )
        )
    console.print(f"[dim]{report['settings']['significance']}[/dim]")
    if "adoption" in report["settings"]:
        console.print(f"[dim]{escape(report['settings']['adoption'])}[/dim]")
    verdict = report["verdict"]
    console.print(f"[bold]Verdict:[/bold] {verdict}; final model: {report['model']}")
    if report.get("power_warning"):
        console.print(f"[yellow]Low power:[/yellow] {escape(report['power_warning'])}")
    if report.get("verdict_is_possible_processing_artefact"):
        console.print(
            f"[yellow]Caution:[/yellow] {report['verdict_is_possible_processing_artefact']}"
        )
