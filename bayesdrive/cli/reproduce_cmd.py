"""``bayesdrive reproduce`` and ``bayesdrive report``: the paper's experiments and their report.

The results folder follows the rule of :mod:`bayesdrive.data.outputs`: it is built beside OUT and
renamed into place when the report is written. An interrupted run resumes with the same
arguments, reusing its finished steps; ``report`` rebuilds a complete folder the same way.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import typer

from bayesdrive.cli.common import FORCE_HELP, console, fail, results_command, results_folder
from bayesdrive.data.errors import DataError
from bayesdrive.data.outputs import OutputError, ResultsFolder, recorded_arguments


def _run(results: ResultsFolder, quick: bool, full: bool, force: bool) -> Path:
    from bayesdrive.experiments.paper import FULL, QUICK, main_steps, run_all
    from bayesdrive.reports.paper_report import build_report

    settings = QUICK if quick else FULL
    started = time.perf_counter()
    try:
        outcome = run_all(
            results.path,
            settings if full else main_steps(settings),
            force=force,
            progress=lambda step: console.print(
                f"[bold]{step}[/bold] ({time.perf_counter() - started:.0f} s)"
            ),
        )
    except (DataError, ValueError, FileNotFoundError) as error:
        raise fail(str(error)) from None
    path = build_report(outcome, results.path, command=["bayesdrive", *sys.argv[1:]])
    folder = results.commit()
    console.print(f"report: {folder / path.name} ({time.perf_counter() - started:.0f} s in all)")
    return folder / path.name


@results_command
def reproduce(
    out: Path = typer.Option(Path("results"), "--out", help="Folder for results and the report."),
    quick: bool = typer.Option(False, "--quick", help="Each step shrunk to run in minutes."),
    full: bool = typer.Option(
        False,
        "--full",
        help="Also the Turing test and the held-out data sets. Over a complete folder of the "
        "same run without --full, only these steps run.",
    ),
    force: bool = typer.Option(False, "--force", help=FORCE_HELP + " Every step is recomputed."),
) -> None:
    """Run the paper's experiments and the criticism on the real data and write out/report.html.

    The Turing test and the held-out data sets run with --full."""
    # A run of the same size without --full is what this one extends.
    extends = {"quick": quick, "full": False} if full and not force else None
    folder = results_folder(out, "reproduce", force=force, resumable=True, extends=extends)
    _run(folder, quick, full, force)


@results_command
def report(
    results: Path = typer.Argument(..., help="A folder written by `bayesdrive reproduce`."),
) -> None:
    """Rebuild the HTML report from saved results (steps not yet run are run)."""
    try:
        arguments = recorded_arguments(results, "reproduce")
    except OutputError as error:
        raise fail(str(error)) from None
    folder = results_folder(
        results, "reproduce", force=False, resumable=True, update=True, arguments=arguments
    )
    # Folders written before --full ran every step.
    _run(folder, arguments["quick"], arguments.get("full", True), force=False)
