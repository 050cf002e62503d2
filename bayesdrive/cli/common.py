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


def fail(message: str, code: int = 2) -> typer.Exit:
    err_console.print(f"[red]error:[/red] {escape(message)}", soft_wrap=True)
    return typer.Exit(code)
