"""``bayesdrive export``: fitted drivers in other tools' formats (SUMO vehicle types)."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.markup import escape

from bayesdrive.cli.common import console, err_console, fail

app = typer.Typer(help="Export fitted drivers to other tools.", no_args_is_help=True)


@app.callback()
def export() -> None:
    """Export fitted drivers to other tools."""
    # A callback keeps `export` a group of formats while SUMO is its only one.


@app.command("sumo")
def sumo(
    result: Path = typer.Argument(..., help="A result.nc from `bayesdrive fit` (or models/)."),
    out: Path = typer.Option(..., "--out", help="The SUMO additional file to write (.xml)."),
    draws: int | None = typer.Option(
        None,
        "--draws",
        min=1,
        help="Draw N drivers from the pooled posterior (default: one "
        "driver per fitted vehicle at its posterior medians).",
    ),
    population: bool = typer.Option(
        False,
        "--population",
        help="Draw the --draws drivers from the hierarchical fit's "
        "population distribution of a new driver instead.",
    ),
    seed: int | None = typer.Option(None, "--seed", help="Seed of the draws (recorded)."),
    stepping: float | None = typer.Option(
        None,
        "--stepping",
        help="SUMO's IDM sub-step, or Krauss' tau for Gipps (s); default: the step "
        "length of the fitted data, recorded in the result.",
    ),
    distribution_id: str | None = typer.Option(
        None, "--id", help="Id of the vTypeDistribution (default: the result file's stem)."
    ),
) -> None:
    """Write a SUMO vTypeDistribution of vehicle types: SUMO's IDM for an IDM result, its Krauss
    for a Gipps result (mappings: bayesdrive.simulation.sumo).

    Use the types with --step-method.ballistic, as bayesdrive integrates positions that way.
    """
    from bayesdrive.inference.core.output import load_result
    from bayesdrive.simulation import sumo as export

    if population and draws is None:
        raise fail("--population draws drivers: give their number with --draws N")
    if draws is not None and seed is None:
        raise fail("--draws needs --seed (every random draw records its seed)")
    if not result.exists():
        raise fail(f"{result}: no such result file")
    tree = load_result(result)
    try:
        if draws is None:
            drivers, how = export.per_vehicle_drivers(tree), "one type per fitted vehicle"
        else:
            import jax

            draw = export.population_drivers if population else export.posterior_drivers
            drivers = draw(jax.random.key(seed), tree, draws)
            how = f"{draws} draws from the {'population' if population else 'pooled posterior'}"
        step = export.fitted_step_length(tree) if stepping is None else stepping
        xml = export.vtype_distribution(
            drivers,
            distribution_id=distribution_id or result.stem,
            stepping=step,
            header=export.export_header(tree, result.name, how, seed if draws else None),
        )
    except ValueError as error:
        raise fail(f"{result}: {error}") from None
    export.write_vtype_distribution(out, xml)
    for name, line in export.NOT_CARRIED.items():
        if name in drivers[0].params:
            err_console.print(escape(line), soft_wrap=True)
    kind = export.SUMO_MODELS[drivers[0].model].car_follow_model
    console.print(f"{len(drivers)} SUMO {kind} vehicle types ({how}, stepping {step:g} s): {out}")
