"""``bayesdrive validate``: do other tools reproduce the fitted drivers? (SUMO, through libsumo.)

The library is :mod:`bayesdrive.simulation.sumo_validation`; this module reads the inputs, prints
the table and writes the results folder.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich.markup import escape
from rich.table import Table

from bayesdrive.cli.common import (
    ForceResults,
    console,
    emit_json,
    fail,
    results_command,
    results_folder,
)

if TYPE_CHECKING:
    from bayesdrive.simulation.sumo_validation import SumoValidation

app = typer.Typer(help="Check fitted drivers in other simulators.", no_args_is_help=True)

JSON_HELP = "Write the summary as JSON to OUT ('-' for standard output, then nothing else there)."


@app.callback()
def validate() -> None:
    """Check fitted drivers in other simulators."""
    # A callback keeps `validate` a group of simulators while SUMO is its only one.


@app.command("sumo")
@results_command
def sumo(
    result: Path = typer.Argument(
        ..., help="An IDM or Gipps result.nc from `bayesdrive fit` (or models/)."
    ),
    data: str = typer.Argument(..., help="The data set it was fitted to: a name or a path."),
    out: Path = typer.Option(
        ..., "--out", help="Folder for the tables, the figure and the summary."
    ),
    horizon: float = typer.Option(5.0, "--horizon", min=0.1, help="Seconds per window."),
    window: str = typer.Option(
        "heldout", "--window", help="Which part of each vehicle: heldout (default), fit or all."
    ),
    vehicles: int | None = typer.Option(
        None, "--vehicles", min=1, help="Only the first N fitted vehicles the data hold."
    ),
    rollouts: int = typer.Option(
        10, "--rollouts", min=1, help="bayesdrive's posterior-predictive rollouts per window."
    ),
    bootstrap: int = typer.Option(
        200, "--bootstrap", min=20, help="Bootstrap resamples of the windows per interval."
    ),
    stepping: float | None = typer.Option(
        None,
        "--stepping",
        help="SUMO's IDM sub-step, or Krauss' tau for Gipps (s); default: the fitted step.",
    ),
    seed: int = typer.Option(0, "--seed", help="Seed of the draws and the bootstrap (recorded)."),
    json_out: str | None = typer.Option(None, "--json", metavar="OUT", help=JSON_HELP),
    force: ForceResults = False,
) -> None:
    """Run the fitted drivers in SUMO behind the data's recorded leaders; compare with the data.

    SUMO's gap, speed and acceleration distributions are compared with bayesdrive's rollouts of
    the same drivers (pass: within the stated tolerance, and a control with one parameter halved
    must fail) and with the data. IDM results run SUMO's IDM, Gipps results its Krauss. Exit code 3 when the check fails (the results are still written).
    """
    if window not in ("heldout", "fit", "all"):
        raise fail(f"--window {window!r}: choose heldout, fit or all")
    if not result.exists():
        raise fail(f"{result}: no such result file")
    folder = results_folder(out, "validate sumo", force=force, json_out=json_out)
    # The libraries load here, not at import: `--help` answers without them.
    import jax

    from bayesdrive.data.errors import DataError
    from bayesdrive.data.registry import load
    from bayesdrive.inference.core.output import load_result
    from bayesdrive.simulation.sumo import fitted_step_length
    from bayesdrive.simulation.sumo_validation import validate_sumo, validated_model

    try:
        tree = load_result(result)
        validated_model(tree)  # before the data load, which takes seconds
        traj = load(data)
        outcome = validate_sumo(
            jax.random.key(seed),
            tree,
            traj,
            horizon_s=horizon,
            window=window,
            num_vehicles=vehicles,
            num_rollouts=rollouts,
            num_bootstrap=bootstrap,
            stepping=fitted_step_length(tree) if stepping is None else stepping,
        )
    except (DataError, OSError, KeyError, ValueError, RuntimeError) as error:
        raise fail(str(error)) from None
    summary = _summary(outcome, seed)
    control = ", ".join(f"{name} x{factor:g}" for name, factor in outcome.control.items())
    title = f"{result.name} in SUMO behind {data}'s leaders (control: {control})"
    _write(outcome, summary, folder.path, title=title)
    folder.commit()
    summary["files"] = [str(out / name) for name in FILES]
    if not emit_json(summary, json_out):
        _print(outcome)
        console.print(f"tables, figure and summary written to {escape(str(out))}")
    if not outcome.passed:
        raise typer.Exit(3)


FILES = ("distances.csv", "windows.csv", "distributions.png", "summary.json")


def _summary(outcome: SumoValidation, seed: int) -> dict[str, Any]:
    from bayesdrive.simulation.sumo_validation import TOLERANCE

    return {
        "passed": outcome.passed,
        "sumo_matches_bayesdrive": outcome.matched,
        "control_failed": outcome.control_failed,
        "control": {name: f"x{factor:g}" for name, factor in outcome.control.items()},
        "tolerance_w1": TOLERANCE,
        "windows": len(outcome.windows.vehicle),
        "vehicles": len(set(outcome.windows.vehicle)),
        "windows_left_out": outcome.left_out,
        "seed": seed,
        # Rows without a tolerance hold None there, not NaN, which JSON lacks.
        "distances": outcome.distances.astype(object)
        .where(outcome.distances.notna(), None)
        .to_dict(orient="records"),
    }


def _write(outcome: SumoValidation, summary: dict[str, Any], staged: Path, *, title: str) -> None:
    import pandas as pd

    from bayesdrive.data.atomic import write_text_atomic
    from bayesdrive.reports.sumo_plots import plot_sumo_distributions
    from bayesdrive.simulation.sumo_validation import QUANTITIES

    write_text_atomic(staged / "distances.csv", outcome.distances.to_csv(index=False))
    windows = pd.DataFrame({"vehicle": outcome.windows.vehicle, "t_start_s": outcome.windows.t0})
    write_text_atomic(staged / "windows.csv", windows.to_csv(index=False))
    plot_sumo_distributions(outcome.samples, QUANTITIES, staged / "distributions.png", title=title)
    write_text_atomic(staged / "summary.json", json.dumps(summary, indent=2, default=str) + "\n")


def _print(outcome: SumoValidation) -> None:
    table = Table(title="1-Wasserstein distance [95% bootstrap interval]", title_justify="left")
    for column in ("compared", "quantity", "W1", "interval", "tolerance", "within"):
        table.add_column(column, justify="left" if column in ("compared", "quantity") else "right")
    for row in outcome.distances.itertuples():
        checked = row.within_tolerance is not None
        table.add_row(
            row.compared,
            f"{row.quantity} ({row.unit})",
            f"{row.w1:.3g}",
            f"[{row.w1_low:.3g}, {row.w1_high:.3g}]",
            f"{row.tolerance:g}" if checked else "",
            ("yes" if row.within_tolerance else "no") if checked else "",
        )
    console.print(table)
    verdict = "PASS" if outcome.passed else "FAIL"
    console.print(
        f"{verdict}: SUMO {'matches' if outcome.matched else 'misses'}"
        f" bayesdrive's rollouts of the same drivers within tolerance; the control "
        f"{'fails, as it must' if outcome.control_failed else 'passes: the check has no power'}"
        f" ({len(outcome.windows.vehicle)} windows)"
    )
