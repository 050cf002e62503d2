"""``bayesdrive reproduce`` and ``bayesdrive report``: the paper's experiments and their report."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import typer

from bayesdrive.cli.common import console, fail
from bayesdrive.data.errors import DataError


def _run(out: Path, settings, force: bool) -> Path:
    from bayesdrive.reports.experiments import run_all
    from bayesdrive.reports.paper_report import build_report

    started = time.perf_counter()
    try:
        results = run_all(
            out,
            settings,
            force=force,
            progress=lambda step: console.print(
                f"[bold]{step}[/bold] ({time.perf_counter() - started:.0f} s)"
            ),
        )
    except (DataError, ValueError, FileNotFoundError) as error:
        raise fail(str(error)) from None
    path = build_report(results, out, command=["bayesdrive", *sys.argv[1:]])
    console.print(f"report: {path} ({time.perf_counter() - started:.0f} s in all)")
    return path


def reproduce(
    out: Path = typer.Option(Path("results"), "--out", help="Folder for results and the report."),
    quick: bool = typer.Option(False, "--quick", help="Every step, shrunk to run in minutes."),
    force: bool = typer.Option(False, "--force", help="Recompute finished steps too."),
) -> None:
    """Run every experiment of the paper on the real data and write out/report.html."""
    from bayesdrive.reports.experiments import FULL, QUICK

    _run(out, QUICK if quick else FULL, force)


def report(
    results: Path = typer.Argument(..., help="A folder written by `bayesdrive reproduce`."),
) -> None:
    """Rebuild the HTML report from saved results (steps not yet run are run)."""
    from bayesdrive.reports.experiments import recorded_settings

    try:
        settings = recorded_settings(results)
    except FileNotFoundError as error:
        raise fail(str(error)) from None
    _run(results, settings, force=False)
