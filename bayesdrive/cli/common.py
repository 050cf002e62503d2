"""Helpers every command shares: the --json convention, data lookup, errors as exit codes."""

from __future__ import annotations

import functools
import json
import os
import signal
import sys
import threading
from collections.abc import Callable
from contextlib import ExitStack
from contextvars import ContextVar
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape

from bayesdrive.data.atomic import existing_ancestor, write_text_atomic
from bayesdrive.data.outputs import OutputError, ResultsFolder, open_results

if TYPE_CHECKING:
    from rich.progress import Progress

console = Console(stderr=False)
err_console = Console(stderr=True)


def progress_bar() -> Progress:
    """A counting progress bar (done of total, time so far), on standard error: standard output
    may carry the JSON."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=err_console,
        transient=True,
    )


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


def check_json_out(out: str | None, force: bool) -> None:
    """Refuse, before any work, a --json OUT that names a folder or lies under a file, or an
    existing file without ``force``: as a complete results folder, it is replaced only on
    request."""
    if out is None or out == "-":
        return
    path = Path(out)
    if path.is_dir():
        raise fail(f"--json {out} is a folder, not a file")
    if path.exists() and not force:
        raise fail(f"--json {out} exists; use --force to replace it")
    ancestor = existing_ancestor(path)
    if not ancestor.is_dir():
        raise fail(f"cannot write --json {out}: {ancestor} is a file, not a folder")


# Options that say where a result goes, where it is computed or whether to replace it, not what
# it is (a cluster run resumes on another cluster, e.g. a scheduler restarted on a new port).
NOT_IDENTITY = ("out", "force", "json_out", "cluster")
FORCE_HELP = "Replace a complete result in OUT (or discard a partial one of other settings)."
JSON_FORCE_HELP = "Replace an existing --json file."
JSON_HELP = "Write the result as JSON to OUT ('-' for standard output, then nothing else there)."
# The options most commands share, declared once (typer reads them from the annotation).
JsonOut = Annotated[str | None, typer.Option("--json", metavar="OUT", help=JSON_HELP)]
# --force of a command that writes a results folder, and of one whose only file is its --json.
ForceResults = Annotated[bool, typer.Option("--force", help=FORCE_HELP)]
ForceJson = Annotated[bool, typer.Option("--force", help=JSON_FORCE_HELP)]
_scope: ContextVar[tuple[ExitStack, dict[str, Any]]] = ContextVar("results_scope")


def results_command(command: Callable[..., None]) -> Callable[..., None]:
    """Run a command that writes a results folder with its arguments at hand, and clean up after it.

    The folder opened by :func:`results_folder` is closed when the command ends, however it ends.
    """

    @functools.wraps(command)
    def run(*args: Any, **kwargs: Any) -> None:
        with ExitStack() as stack:
            token = _scope.set((stack, kwargs))
            try:
                command(*args, **kwargs)
            except Exception:
                # Code that turns every error into one of its own (a C++ callback's caller) can
                # turn the signal's exit into an error: the signal decides the exit code.
                if _received:
                    raise SystemExit(128 + _received[-1]) from None
                raise
            finally:
                _scope.reset(token)

    return run


# The signal that ended this process's command, once one has come.
_received: list[int] = []
# Long enough for the ignoring callback to return, short beside any command.
RESEND_AFTER_S = 0.05


def _terminated(signum: int, frame: Any) -> None:
    # Unwinds like any error, so temporary files are removed on the way out.
    _received.append(signum)
    raise SystemExit(128 + signum)


def _resend_a_lost_signal(previous_hook: Callable[[Any], None], unraisable: Any) -> None:
    """Python ignores an error raised where nothing can catch it (a garbage-collector callback,
    such as JAX's, or a ``__del__``), so a SIGTERM whose handler ran there would be lost and the
    command would go on: send it again, to end the command from where it is next. (Sent from
    here at once, its handler would run here again and be ignored again; so a timer thread sends
    it once this hook has returned, and a signal lost again is sent again.)"""
    if isinstance(unraisable.exc_value, SystemExit) and _received:
        resend = threading.Timer(RESEND_AFTER_S, os.kill, args=(os.getpid(), _received[-1]))
        resend.daemon = True
        resend.start()
        return
    previous_hook(unraisable)


def exit_cleanly_on_sigterm() -> None:
    """Until the command ends, SIGTERM exits with code 143 after removing temporary files."""
    stack, _ = _scope.get()
    if threading.current_thread() is threading.main_thread():
        _received.clear()
        previous = signal.signal(signal.SIGTERM, _terminated)
        stack.callback(signal.signal, signal.SIGTERM, previous)
        previous_hook = sys.unraisablehook
        sys.unraisablehook = functools.partial(_resend_a_lost_signal, previous_hook)
        stack.callback(setattr, sys, "unraisablehook", previous_hook)


def results_folder(
    out: str | Path,
    command: str,
    *,
    force: bool,
    json_out: str | None = None,
    resumable: bool = False,
    update: bool = False,
    arguments: dict[str, Any] | None = None,
    extends: dict[str, Any] | None = None,
) -> ResultsFolder:
    """Check OUT (and the command's ``json_out``, :func:`check_json_out`) before any work and open
    its staging folder (:mod:`bayesdrive.data.outputs`).

    The arguments recorded are the command's own (less where the result goes) unless given;
    ``extends`` are those of a complete folder this run may extend. SIGTERM is handled as
    :func:`exit_cleanly_on_sigterm` says.
    """
    check_json_out(json_out, force)
    stack, kwargs = _scope.get()
    if arguments is None:
        arguments = {k: v for k, v in kwargs.items() if k not in NOT_IDENTITY}
    exit_cleanly_on_sigterm()
    try:
        folder = open_results(
            out,
            command,
            arguments,
            force=force,
            resumable=resumable,
            update=update,
            extends=extends,
        )
    except OutputError as error:
        raise fail(str(error)) from None
    stack.enter_context(folder)
    if folder.resumed:
        reused = "reusing its finished steps" if resumable else "starting it again"
        err_console.print(
            escape(f"{folder.path}: an interrupted run with the same arguments; {reused}"),
            soft_wrap=True,
        )
    return folder


def optional_results(
    out: str | Path | None, command: str, *, json_out: str | None, force: bool
) -> ResultsFolder | None:
    """:func:`results_folder` of a command whose OUT is optional: without one, only its
    ``json_out`` is checked (and None returned)."""
    if out is None:
        check_json_out(json_out, force)
        return None
    return results_folder(out, command, force=force, json_out=json_out)


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
ColumnMap = Annotated[str | None, typer.Option("--columns", help=COLUMNS_HELP)]
LengthUnits = Annotated[str | None, typer.Option("--units", help=UNITS_HELP)]


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


def check_cluster_options(cluster: str | None, chunk_size: int | None) -> None:
    """Refuse ``--chunk-size`` without ``--cluster``, and a malformed ``--cluster`` or one without
    Dask installed, before any work."""
    if chunk_size is not None and cluster is None:
        raise fail("--chunk-size applies to --cluster only")
    if cluster is not None:
        from bayesdrive.inference.distributed import cluster_workers  # imports JAX: not at start-up

        try:
            cluster_workers(cluster)
        except ValueError as error:
            raise fail(str(error)) from None


def fail(message: str, code: int = 2) -> typer.Exit:
    err_console.print(f"[red]error:[/red] {escape(message)}", soft_wrap=True)
    return typer.Exit(code)
