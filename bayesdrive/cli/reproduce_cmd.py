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


def _run(results: ResultsFolder, quick: bool, force: bool) -> Path:
    from bayesdrive.experiments.paper import FULL, QUICK, run_all
    from bayesdrive.reports.paper_report import build_report

    started = time.perf_counter()
    try:
        outcome = run_all(
            results.path,
            QUICK if quick else FULL,
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
    quick: bool = typer.Option(False, "--quick", help="Every step, shrunk to run in minutes."),
    force: bool = typer.Option(False, "--force", help=FORCE_HELP + " Every step is recomputed."),
) -> None:
    """Run every experiment of the paper on the real data and write out/report.html."""
    _run(results_folder(out, "reproduce", force=force, resumable=True), quick, force)


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
    _run(folder, arguments["quick"], force=False)
