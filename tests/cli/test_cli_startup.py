"""Help answers without importing the heavy libraries; the top-level command list is true.

Speed itself is measured in ``benchmarks/bench_cli_startup.py`` (``reports/cli_startup.md``); here
only what makes it fast: ``bayesdrive --help``, ``--version`` and the ``--help`` of every command
and subcommand import none of the libraries that take seconds (JAX above all), and every command
summary the top-level help lists is the command's own help.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from bayesdrive import __version__
from bayesdrive.cli.main import COMMANDS, app, load_command
from benchmarks.bench_cli_startup import heavy_imports, heavy_imports_each, help_commands

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("args", [["--help"], ["--version"]])
def test_top_level_imports_no_heavy_library(args):
    assert heavy_imports(args) == []


def test_no_command_or_subcommand_help_imports_a_heavy_library():
    commands = help_commands()
    assert ("fit", "--help") in commands and ("data", "info", "--help") in commands
    # One process runs them all in turn: a library listed after a command came in with it.
    loaded = heavy_imports_each(commands)
    first = next(((c, found) for c, found in zip(commands, loaded, strict=True) if found), None)
    assert first is None, f"`bayesdrive {' '.join(first[0])}` imported {', '.join(first[1])}"


def test_negative_control_a_command_that_runs_does_import_them():
    # The probe sees imports at all: diagnose imports JAX and ArviZ before it finds no file.
    assert {"jax", "arviz"} <= set(heavy_imports(["diagnose", "no-such-result.nc"]))


def test_version():
    result = CliRunner().invoke(app, ["--version"])
    assert result.exit_code == 0
    assert result.output.strip() == f"bayesdrive {__version__}"


@pytest.mark.parametrize("name", list(COMMANDS))
def test_listed_summary_is_the_commands_own_help(name):
    command = load_command(name)
    assert command.help.strip().splitlines()[0] == COMMANDS[name].summary


def test_help_lists_every_command():
    result = CliRunner().invoke(app, ["--help"])
    assert result.exit_code == 0
    for name in COMMANDS:
        assert name in result.output


def test_names_the_help_shows_are_the_librarys():
    from bayesdrive.cli import names
    from bayesdrive.drivers.extensions import CAUSES
    from bayesdrive.drivers.idm import IDM
    from bayesdrive.drivers.registry import MODELS
    from bayesdrive.inference.distributed import DEFAULT_CHUNK_SIZE
    from bayesdrive.inference.fit import ENGINES
    from bayesdrive.simulation.baselines import BASELINES
    from bayesdrive.simulation.evaluation import DEFAULT_SCENARIO_CHUNK

    assert tuple(MODELS) == names.MODELS
    assert names.CAUSES == CAUSES
    assert tuple(ENGINES) == names.ENGINES
    assert tuple(BASELINES) == names.BASELINES
    assert IDM.param_names == names.IDM_PARAMS
    assert names.FIT_CHUNK_SIZE == DEFAULT_CHUNK_SIZE
    assert names.SCENARIO_CHUNK_SIZE == DEFAULT_SCENARIO_CHUNK
