"""Every code block of the README runs as written, so the tours can never break again.

Blocks run in README order in one temporary folder (what they write lands there), with
``$BAYESDRIVE_DATA_DIR`` set to the real data: shell blocks line by line, each line a
``bayesdrive`` command run in-process through typer's CliRunner (``$VARS`` expanded, ``#``
comments dropped; one process keeps JAX's compilations between commands), Python blocks through
``exec`` (in one namespace, as a reader types them one after another). A block the test does not run is listed in :data:`NOT_RUN` with the test that covers
it; an entry that no longer matches a block fails, so the list cannot go stale.

Both tours are in the ``extended`` tier, which CI leaves out (README, reports/ci_time.md): the
CLI tour (tiny settings, but every engine compiles once) takes minutes, and each of its commands
has tests of its own in CI. The check of the block list, and that every Python block compiles, run
in CI.
"""

from __future__ import annotations

import os
import re
import shlex
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bayesdrive.cli.main import app

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCK = re.compile(r"^```(\w*)\n(.*?)^```$", re.DOTALL | re.MULTILINE)

# The first line of each block that is not run here -> what runs it instead.
NOT_RUN = {
    "python3.12 -m venv .venv && .venv/bin/pip install -e . && .venv/bin/bayesdrive reproduce "
    "--out results": "the main job (full sizes, beyond a test's time); tests/experiments/test_reproduce.py runs its quick "
    "form, `reproduce --quick`, then `--full` over it, and `report` on what they wrote",
    'python3.12 -m venv .venv && .venv/bin/pip install -e ".[test]" && .venv/bin/ruff check . && '
    '.venv/bin/ruff format --check . && .venv/bin/pytest -q -n 2 --dist worksteal -m "not extended" '
    "--durations=20": "the test command: CI runs it (.ci/run reads it from the README)",
    "dask scheduler --port 8786                       # on one machine": "starts a Dask "
    "cluster; tests/inference/test_cluster.py runs `fit --cluster` on a local one, through its address",
}
# Lines of a run block that are not run here -> what runs them instead.
LINES_NOT_RUN = {
    "bayesdrive reproduce --quick --out results-quick": "tests/experiments/test_reproduce.py",
    "bayesdrive report results-quick": "tests/experiments/test_reproduce.py (`report` on a quick run)",
}


def blocks() -> list[tuple[str, str]]:
    """(language, text) of every fenced code block, in order."""
    return [(lang, text) for lang, text in BLOCK.findall(README.read_text())]


def _first_line(text: str) -> str:
    return text.strip().splitlines()[0]


def _commands(text: str) -> list[str]:
    """The block's commands, comments dropped."""
    lines = (re.split(r"\s+#", line, maxsplit=1)[0].strip() for line in text.splitlines())
    return [line for line in lines if line]


def test_every_block_is_run_or_names_what_runs_it():
    found = blocks()
    assert len(found) >= 5
    firsts = [_first_line(text) for _, text in found]
    for listed in NOT_RUN:
        assert listed in firsts, f"NOT_RUN lists a block the README no longer has: {listed}"
    commands = [c for lang, text in found if lang != "python" for c in _commands(text)]
    for listed in LINES_NOT_RUN:
        assert listed in commands, f"LINES_NOT_RUN lists a line the README no longer has: {listed}"
    for lang, text in found:
        if _first_line(text) in NOT_RUN:
            continue
        if lang == "python":
            compile(text, "README.md", "exec")
        else:
            assert all(c.startswith("bayesdrive ") for c in _commands(text)), text


@pytest.fixture
def in_scratch(data_dir, tmp_path, monkeypatch):
    monkeypatch.setenv("BAYESDRIVE_DATA_DIR", str(data_dir))
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _run_shell_block(text: str) -> None:
    runner = CliRunner()
    for command in _commands(text):
        if command in LINES_NOT_RUN:
            continue
        args = shlex.split(os.path.expandvars(command))[1:]
        result = runner.invoke(app, args)
        assert result.exit_code == 0, f"{command}\n{result.output}"


@pytest.mark.extended
@pytest.mark.realdata
def test_python_tour_runs_as_written(in_scratch):
    namespace = {"__name__": "readme"}  # shared: later blocks continue the earlier ones
    for lang, text in blocks():
        if lang == "python":
            exec(compile(text, "README.md", "exec"), namespace)


@pytest.mark.extended
@pytest.mark.slow
@pytest.mark.realdata
def test_cli_tour_runs_as_written(in_scratch):
    tours = [
        text for lang, text in blocks() if lang != "python" and _first_line(text) not in NOT_RUN
    ]
    assert tours
    for text in tours:
        _run_shell_block(text)
    assert (in_scratch / "fetched" / "ngsim_i80_chains").is_dir()
    assert (in_scratch / "runs" / "smc" / "result.nc").is_file()
    criticism = (in_scratch / "runs" / "criticism.json").read_text()
    assert "only 2 vehicle(s) criticized" in criticism
