"""The ``bayesdrive`` command: one typer app, one sub-module per command (group).

A command's module is imported only when that command runs (or shows its own help), and imports
JAX, pandas and ArviZ, which take seconds, only inside its command functions (the names its help
lists come from :mod:`bayesdrive.cli.names`): every ``--help`` and ``--version`` answers at once. :data:`COMMANDS` names where each command lives and the one-line summary the
top-level help lists (``tests/cli/test_cli_startup.py`` checks that each equals the first line of
the command's own help).
"""

from __future__ import annotations

import importlib
import logging
import os
from typing import NamedTuple

import typer
from typer.core import TyperCommand, TyperGroup

from bayesdrive import __version__


class LazyCommand(NamedTuple):
    module: str
    attribute: str  # a command function, or a typer app for a command group
    summary: str


COMMANDS: dict[str, LazyCommand] = {
    "data": LazyCommand(
        "bayesdrive.cli.data_cmd", "app", "List, inspect, verify and fetch trajectory data sets."
    ),
    "export": LazyCommand(
        "bayesdrive.cli.export_cmd", "app", "Export fitted drivers to other tools."
    ),
    "validate": LazyCommand(
        "bayesdrive.cli.validate_cmd", "app", "Check fitted drivers in other simulators."
    ),
    "fit": LazyCommand(
        "bayesdrive.cli.fit_cmd",
        "fit",
        "Fit per-vehicle parameter distributions and write result.nc, summary.json and plots.",
    ),
    "evaluate": LazyCommand(
        "bayesdrive.cli.evaluate_cmd",
        "evaluate",
        "Roll a model out closed loop on the held-out windows and print the metric table.",
    ),
    "simulate": LazyCommand(
        "bayesdrive.cli.simulate_cmd",
        "simulate",
        "Generate scenes of VEHICLES cars for DURATION seconds; write trajectories, figures, "
        "summary.",
    ),
    "reproduce": LazyCommand(
        "bayesdrive.cli.reproduce_cmd",
        "reproduce",
        "Run the paper's experiments and the criticism on the real data and write out/report.html.",
    ),
    "report": LazyCommand(
        "bayesdrive.cli.reproduce_cmd",
        "report",
        "Rebuild the HTML report from saved results (steps not yet run are run).",
    ),
    "diagnose": LazyCommand(
        "bayesdrive.cli.diagnose_cmd",
        "diagnose",
        "Convergence of each result and, for several results on the same data, their agreement.",
    ),
    "sbc": LazyCommand(
        "bayesdrive.cli.sbc_cmd",
        "sbc",
        "Simulation-based calibration: are the engine's posteriors calibrated on the model?",
    ),
    "criticize": LazyCommand(
        "bayesdrive.cli.criticize_cmd",
        "criticize_command",
        "Fit the model, check it, name the cause of its misfit, adopt it if it simulates better.",
    ),
}


def load_command(name: str) -> TyperCommand:
    """The click command ``name``, its module imported now."""
    entry = COMMANDS[name]
    target = getattr(importlib.import_module(entry.module), entry.attribute)
    if isinstance(target, typer.Typer):
        return typer.main.get_command(target)
    single = typer.Typer()
    single.command(name)(target)
    return typer.main.get_command(single)


class LazyGroup(TyperGroup):
    """Lists every command from :data:`COMMANDS`; imports one only to run it or show its help."""

    def list_commands(self, ctx: typer.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: typer.Context, cmd_name: str) -> TyperCommand | None:
        if cmd_name in self.commands or cmd_name not in COMMANDS:
            return self.commands.get(cmd_name)
        # Enough for the top-level help's list; resolve_command swaps in the real command.
        return TyperCommand(cmd_name, help=COMMANDS[cmd_name].summary)

    def resolve_command(self, ctx: typer.Context, args: list[str]):
        if args and args[0] in COMMANDS and args[0] not in self.commands:
            self.commands[args[0]] = load_command(args[0])
        return super().resolve_command(ctx, args)


app = typer.Typer(
    cls=LazyGroup,
    help="Learn distributions over rule-based driver-model parameters from real trajectories.",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
)


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"bayesdrive {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log repairs and flags."),
    version: bool = typer.Option(
        False, "--version", callback=_print_version, is_eager=True, help="Print the version."
    ),
):
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(message)s")


def one_device_per_core() -> None:
    """Give JAX one CPU device per available core, unless ``XLA_FLAGS`` sets a device count.

    Engines split each chunk of vehicles over the local devices, each running the same program,
    so this changes no result bit; one device per core keeps every core busy where XLA's own
    threads leave most of the second idle (``reports/scaling.md``). No effect on a GPU, whose
    devices JAX uses instead. It must run before JAX starts its CPU backend."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" not in flags:
        cores = len(os.sched_getaffinity(0))
        os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={cores}".strip()


COMPILATION_CACHE_ENV = "BAYESDRIVE_COMPILATION_CACHE"
# Programs that compile faster than this are not worth a disk entry.
CACHE_MIN_COMPILE_S = 0.1


def compilation_cache() -> None:
    """Keep JAX's compiled programs on disk, so a later run with the same shapes skips compiling.

    The folder is ``$BAYESDRIVE_COMPILATION_CACHE``, or ``$XDG_CACHE_HOME/bayesdrive/jax`` (else
    ``~/.cache/bayesdrive/jax``); ``BAYESDRIVE_COMPILATION_CACHE=off`` turns it off. A
    ``JAX_COMPILATION_CACHE_DIR`` already set is left as it is. A cached program is the compiled
    one, so results are the same bits with or without it (``tests/inference/test_determinism.py``). It must
    run before JAX is imported, which reads these variables then."""
    if "JAX_COMPILATION_CACHE_DIR" in os.environ:
        return
    folder = os.environ.get(COMPILATION_CACHE_ENV)
    if folder == "off":
        return
    if not folder:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        folder = os.path.join(base, "bayesdrive", "jax")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = folder
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", str(CACHE_MIN_COMPILE_S))


def entry() -> None:
    """The ``bayesdrive`` console script."""
    one_device_per_core()
    compilation_cache()
    app()


if __name__ == "__main__":
    entry()
