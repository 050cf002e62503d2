"""The top-level command answers without importing the heavy libraries; its command list is true.

Speed itself is measured in ``benchmarks/bench_cli_startup.py`` (``reports/cli_startup.md``); here
only what makes it fast: ``bayesdrive --help`` and ``--version`` import none of the libraries that
take seconds, and every command summary they list is the command's own help.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from bayesdrive import __version__
from bayesdrive.cli.main import COMMANDS, app, load_command
from benchmarks.bench_cli_startup import heavy_imports

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("args", [["--help"], ["--version"]])
def test_top_level_imports_no_heavy_library(args):
    assert heavy_imports(args) == []


def test_negative_control_a_command_does_import_them():
    # The probe sees imports at all: running a command's help loads JAX.
    assert "jax" in heavy_imports(["fit", "--help"])


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
