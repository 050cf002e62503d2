"""``bayesdrive data``: list, inspect, verify and fetch data sets.

Bad input (an unreadable file, an unknown name, a missing data set, a failed checksum) ends with a
one-line ``error: ...`` on standard error and exit code 2, never a traceback.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich.markup import escape
from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from bayesdrive.cli.common import (
    ColumnMap,
    ForceJson,
    JsonOut,
    LengthUnits,
    check_json_out,
    column_map_options,
    console,
    emit_json,
    err_console,
    exit_cleanly_on_sigterm,
    fail,
    results_command,
)
from bayesdrive.data.errors import DataError

if TYPE_CHECKING:
    from bayesdrive.data.registry import DataSet

__all__ = ["app"]

app = typer.Typer(
    help="List, inspect, verify and fetch trajectory data sets.", no_args_is_help=True
)

DATA_DIR_HELP = (
    "Folder holding the data sets (default: $BAYESDRIVE_DATA_DIR, else ../shared/data beside the "
    "repository); for a held-out data set, the holdout folder ($BAYESDRIVE_HOLDOUT_DIR)."
)


def _error(error: Exception) -> typer.Exit:
    # Messages quote file contents and paths: never let rich read them as markup.
    return fail(str(error))


def _root(dataset: DataSet, explicit: str | None) -> Path:
    # The readers behind the registry import pandas: not needed for `bayesdrive data --help`.
    from bayesdrive.data import registry

    if dataset.role == "holdout":
        return registry.holdout_dir(explicit)
    return registry.data_dir(explicit)


def _status(dataset: DataSet, explicit: str | None) -> str:
    """'yes' (every file as pinned), 'no', 'differs: N file(s)', or why it cannot be told."""
    from bayesdrive.data import registry

    try:
        folder = _root(dataset, explicit) / dataset.name
    except DataError:
        return "no data dir"
    if not folder.is_dir():
        return "no"
    mismatches = registry.verify(dataset.name, folder.parent)
    return f"differs: {len(mismatches)} file(s)" if mismatches else "yes"


@app.command("list")
def list_datasets(
    data_dir: str | None = typer.Option(None, "--data-dir", help="Folder holding the data sets."),
    holdout_dir: str | None = typer.Option(
        None, "--holdout-dir", help="Folder holding the held-out data sets."
    ),
    json_out: JsonOut = None,
    force: ForceJson = False,
) -> None:
    """The known data sets: format, role, whether present (and verified), licence."""
    from bayesdrive.data import registry

    check_json_out(json_out, force)
    rows = []
    for dataset in (*registry.DATASETS.values(), *registry.HOLDOUT.values()):
        explicit = holdout_dir if dataset.role == "holdout" else data_dir
        rows.append(
            {
                "name": dataset.name,
                "format": dataset.format,
                "role": dataset.role,
                "present": _status(dataset, explicit),
                "licence": dataset.licence,
                "files": len(dataset.files),
                "description": dataset.description,
            }
        )
    if emit_json(rows, json_out):
        return
    table = Table(title="Data sets ('present': every file matches its pinned sha256)")
    for column in ("name", "format", "role", "present"):
        table.add_column(column, no_wrap=True)
    table.add_column("licence")
    for row in rows:
        table.add_row(
            *(escape(str(row[c])) for c in ("name", "format", "role", "present", "licence"))
        )
    console.print(table)
    console.print(
        "Held-out data sets are for evaluation only: never fit, tune or choose anything on them."
    )


def _flatten(result: dict[str, Any], prefix: str = "") -> list[tuple[str, str]]:
    rows = []
    for key, value in result.items():
        if key in ("notes", "flags", "drivers"):
            continue
        if isinstance(value, dict):
            rows.extend(_flatten(value, f"{prefix}{key}."))
        elif isinstance(value, float):
            rows.append((prefix + key, f"{value:.6g}"))
        else:
            rows.append((prefix + key, str(value)))
    return rows


@app.command()
def info(
    path_or_name: str = typer.Argument(..., help="A file, a folder, or a data set name."),
    format: str | None = typer.Option(
        None, "--format", help="Reader to use (default: the data set's, else detected)."
    ),
    data_dir: str | None = typer.Option(None, "--data-dir", help=DATA_DIR_HELP),
    strict: bool = typer.Option(
        False, "--strict", help="Refuse data that needs any repair instead of repairing it."
    ),
    columns: ColumnMap = None,
    units: LengthUnits = None,
    headway: str | None = typer.Option(
        None, "--headway", help="What the CSV's gap column measures: front (to front) or bumper."
    ),
    json_out: JsonOut = None,
    force: ForceJson = False,
) -> None:
    """Figures of a data set: scenes, vehicles, time, speeds, gaps, flags and notes."""
    from bayesdrive.data import registry
    from bayesdrive.data.trajectories import summary

    check_json_out(json_out, force)
    try:
        format, options = column_map_options(format, columns, units, headway)
        traj = registry.load_any(
            path_or_name,
            format=format,
            data_dir=data_dir,
            strict=strict,
            note_held_out=False,
            **options,
        )
    except (DataError, OSError) as error:
        raise _error(error) from None
    result = summary(traj)
    if emit_json(result, json_out):
        return
    table = Table(title=escape(f"{result['source']} ({result['format']})"))
    table.add_column("figure")
    table.add_column("value", justify="right")
    for key, value in _flatten(result):
        table.add_row(key, escape(value))
    for driver, count in result["drivers"].items():
        table.add_row(f"vehicles driven by: {driver}", str(count))
    console.print(table)
    for kind, count in result["flags"].items():
        console.print(f"flagged ({escape(kind)}): {count} sample(s), left out of fitting")
    for note in result["notes"]:
        console.print(f"note: {escape(note)}")


@app.command()
def verify(
    name: str = typer.Argument(..., help="A data set name."),
    data_dir: str | None = typer.Option(None, "--data-dir", help=DATA_DIR_HELP),
    json_out: JsonOut = None,
    force: ForceJson = False,
) -> None:
    """Check every file of a data set against its pinned size and sha256 (exit 1 if any differ)."""
    from bayesdrive.data import registry

    check_json_out(json_out, force)
    try:
        dataset = registry.get(name)
        root = _root(dataset, data_dir)
    except DataError as error:
        raise _error(error) from None
    mismatches = registry.verify(name, root)
    result = {
        "name": name,
        "path": str(root / name),
        "ok": not mismatches,
        "mismatches": [m._asdict() for m in mismatches],
    }
    if not emit_json(result, json_out):
        for mismatch in mismatches:
            console.print(escape(str(mismatch)))
        verdict = "differs from" if mismatches else "matches"
        console.print(escape(f"{root / name} {verdict} the registry ({len(dataset.files)} files)"))
    if mismatches:
        raise typer.Exit(1)


@app.command()
@results_command
def fetch(
    name: str = typer.Argument(..., help="A data set name (see `bayesdrive data list`)."),
    data_dir: str | None = typer.Option(
        None, "--data-dir", help="Folder to fetch into (default as for the other commands)."
    ),
    mirror: str | None = typer.Option(
        None,
        "--mirror",
        help="Base URL of a mirror serving <URL>/<name>/<file> (default: the pinned origin).",
    ),
    json_out: JsonOut = None,
    force: ForceJson = False,
) -> None:
    """Download a data set, checking every sha256 before anything lands in the data folder."""
    from bayesdrive.data import registry
    from bayesdrive.data.fetch import fetch as fetch_dataset
    from bayesdrive.data.fetch import files_to_fetch

    check_json_out(json_out, force)
    exit_cleanly_on_sigterm()
    try:
        dataset = registry.get(name)
        root = _root(dataset, data_dir)
        wanted, _ = files_to_fetch(dataset, mirror)
        with Progress(
            TextColumn(f"fetching {escape(name)}"),
            BarColumn(),
            DownloadColumn(),
            TimeRemainingColumn(),
            console=err_console,
            transient=True,
            disable=not err_console.is_terminal,  # no bar (nor blank lines) in logs and pipes
        ) as progress:
            task = progress.add_task(name, total=sum(f.size for f in wanted))
            result = fetch_dataset(
                name,
                root,
                base_url=mirror,
                progress=lambda received: progress.advance(task, received),
            )
    except (DataError, OSError) as error:
        raise _error(error) from None
    report = result._asdict() | {"path": str(result.path)}
    if emit_json(report, json_out):
        return
    if result.already_present:
        console.print(escape(f"{result.path} already holds {name} as pinned; nothing fetched"))
    else:
        console.print(escape(f"fetched {len(result.fetched)} file(s) into {result.path}, verified"))
    if result.not_published:
        console.print(
            escape(
                "not published at the origin (copy them from a mirror): "
                + ", ".join(result.not_published)
            )
        )
