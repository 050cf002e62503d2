"""Helpers every command shares: the --json convention, data lookup, errors as exit codes."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import typer
from rich.console import Console
from rich.markup import escape

from bayesdrive.data.atomic import write_text_atomic

console = Console(stderr=False)
err_console = Console(stderr=True)


def emit_json(result: Any, out: str | None) -> bool:
    """Write ``result`` as JSON to the file ``out`` (atomically), or to stdout when ``out == "-"``.

    Returns True when stdout was used, so the caller prints nothing else there.
    """
    if out is None:
        return False
    text = json.dumps(result, indent=2, default=_jsonable) + "\n"
    if out == "-":
        sys.stdout.write(text)
        return True
    write_text_atomic(Path(out), text)
    return False


def _jsonable(value):
    if hasattr(value, "item"):
        return value.item()
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"cannot write {type(value).__name__} as JSON")


COLUMN_MAP_FORMAT = "columns"
COLUMNS_HELP = (
    "Column map for an arbitrary CSV: SCHEMA=FILE_COLUMN,... (e.g. vehicle_id=ID,t=time,x=pos,"
    "v=speed); implies --format columns (so do --units and --headway)."
)
UNITS_HELP = "Length unit of an arbitrary CSV: m, ft, or a factor to metres."


def column_map_options(
    format: str | None, columns: str | None, units: str | None, headway: str | None = None
) -> tuple[str | None, dict[str, Any]]:
    """The reader format and options that ``--columns``, ``--units`` and ``--headway`` ask for:
    the column-map reader's when any is given (only those given), else ``format`` and none."""
    from bayesdrive.data.errors import DataError

    mapping = None
    if columns is not None:
        mapping = {}
        for item in columns.split(","):
            schema_name, equals, file_name = item.partition("=")
            if not equals or not schema_name.strip() or not file_name.strip():
                raise DataError(
                    f"--columns: {item!r} is not SCHEMA=FILE_COLUMN "
                    "(e.g. --columns vehicle_id=ID,t=time,x=pos,v=speed)"
                )
            mapping[schema_name.strip()] = file_name.strip()
    given = {"columns": mapping, "units": units, "headway": headway}
    options = {key: value for key, value in given.items() if value is not None}
    if not options:
        return format, options
    # These options belong to the column-map reader; other readers know their units.
    if format not in (None, COLUMN_MAP_FORMAT):
        raise DataError(
            f"--columns, --units and --headway are options of --format {COLUMN_MAP_FORMAT}, "
            f"not of {format}"
        )
    return COLUMN_MAP_FORMAT, options


def fail(message: str, code: int = 2) -> typer.Exit:
    err_console.print(f"[red]error:[/red] {escape(message)}", soft_wrap=True)
    return typer.Exit(code)
