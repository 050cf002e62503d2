"""Results folders are all of one run or none of it (:mod:`bayesdrive.data.outputs`).

A real ``bayesdrive fit`` process is killed (SIGKILL, SIGTERM) at a random moment of its run,
drawn with a fixed seed given in every assertion message; the folder must then be the previous
complete result, absent, or a staging folder the next run recognises. Fits use the paper's filter
(64 particles) on one vehicle of one chain file: a cheap real fit that draws its pictures too.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bayesdrive.cli.main import COMMANDS, app, load_command
from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.data.outputs import (
    MANIFEST,
    OutputError,
    ResultsFolder,
    open_results,
    staging_path,
)
from bayesdrive.inference.core import output
from bayesdrive.inference.core.output import load_result, metadata

REPO = Path(__file__).resolve().parents[2]
CHAIN = "ngsim_i80_chains/124_136_140_146_162_164.csv"
FIT_FILES = {"convergence.png", "ess.png", "manifest.json", "result.nc", "summary.json"}
FIT_FILES |= {"unique_particles.png"}
# Seed of the moments the processes are killed at.
KILL_SEED = 20261123

runner = CliRunner()


def fit_args(data_dir: Path, out: Path, seed: int) -> list[str]:
    return [
        "fit",
        str(data_dir / CHAIN),
        *("--engine", "pf", "--vehicles", "1", "--particles", "64"),
        *("--params", "v_des,sigma", "--seed", str(seed), "--out", str(out)),
    ]


def one_line(text: str) -> str:
    return " ".join(text.split())


def assert_complete(out: Path, seed: int) -> None:
    """``out`` holds one run's files, every one of them from the run with ``seed``."""
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["complete"] is True and manifest["seed"] == seed
    assert {p.name for p in out.iterdir()} == FIT_FILES
    assert set(manifest["files"]) == FIT_FILES - {MANIFEST}
    assert json.loads((out / "summary.json").read_text())["seed"] == seed
    assert metadata(load_result(out / "result.nc"))["seed"] == seed


def leftovers(folder: Path) -> list[str]:
    """Temporary files of atomic writes, anywhere under ``folder``."""
    return [str(p) for p in folder.rglob("*.tmp-*")]


def start_and_kill(args: list[str], out: Path, sig: int, delay: float, after: str) -> int:
    """Run ``bayesdrive ARGS``; ``delay`` s after the file ``after`` appears in its staging
    folder, send ``sig``."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "MPLBACKEND": "Agg"}
    process = subprocess.Popen(
        [sys.executable, "-c", "from bayesdrive.cli.main import app; app()", *args],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    sign = staging_path(out) / after
    deadline = time.monotonic() + 180
    while not sign.exists() and process.poll() is None:
        assert time.monotonic() < deadline, f"the fit never wrote {sign}"
        time.sleep(0.02)
    time.sleep(delay)
    process.send_signal(sig)
    return process.wait(timeout=120)


@pytest.fixture(scope="module")
def old_result(data_dir, tmp_path_factory) -> Path:
    """A complete fit (seed 1), copied by each test that replaces it."""
    out = tmp_path_factory.mktemp("old") / "fit"
    run = runner.invoke(app, fit_args(data_dir, out, 1))
    assert run.exit_code == 0, run.output
    return out


def copy_of(folder: Path, where: Path) -> Path:
    where.mkdir()
    for path in folder.iterdir():
        (where / path.name).write_bytes(path.read_bytes())
    return where


@pytest.mark.realdata
def test_sigkill_at_a_random_moment_leaves_the_old_or_the_new_result(
    old_result, data_dir, tmp_path
):
    out = copy_of(old_result, tmp_path / "fit")
    # The moment is drawn in the writing of the files (summary.json comes first), where a folder
    # written in place would mix two runs; earlier the staging folder holds only its manifest.
    delay = random.Random(KILL_SEED).uniform(0.0, 1.5)
    args = [*fit_args(data_dir, out, 2), "--force"]
    code = start_and_kill(args, out, signal.SIGKILL, delay, after="summary.json")
    where = f"SIGKILL {delay:.2f} s after summary.json (seed {KILL_SEED}), exit {code}"
    # Whatever the moment: a whole run's folder, never a mix, and no half-written file in it.
    seed = json.loads((out / MANIFEST).read_text())["seed"]
    assert seed in (1, 2), where
    assert_complete(out, seed)
    assert leftovers(out) == [], where
    # The next run recognises what was left and finishes.
    again = runner.invoke(app, args)
    assert again.exit_code == 0, again.output
    assert_complete(out, 2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit"], where


@pytest.mark.realdata
def test_sigterm_removes_temporary_files_and_exits_non_zero(old_result, data_dir, tmp_path):
    out = copy_of(old_result, tmp_path / "fit")
    delay = random.Random(KILL_SEED + 1).uniform(0.0, 3.0)
    args = [*fit_args(data_dir, out, 2), "--force"]
    code = start_and_kill(args, out, signal.SIGTERM, delay, after=MANIFEST)
    where = f"SIGTERM {delay:.2f} s after the staging folder (seed {KILL_SEED + 1}), exit {code}"
    # The manifest is written last, so the command has usually ended when the signal comes: the
    # process has exited (0), or it is still shutting down with the default handler back (-15).
    if code in (0, -signal.SIGTERM):
        assert_complete(out, 2)
    else:
        assert code == 128 + signal.SIGTERM, where
        assert_complete(out, 1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit"], where  # no staging folder
    assert leftovers(tmp_path) == [], where


@pytest.mark.realdata
def test_a_complete_result_is_kept_unless_force(old_result, data_dir, tmp_path):
    out = copy_of(old_result, tmp_path / "fit")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    refused = runner.invoke(app, fit_args(data_dir, out, 2))
    assert refused.exit_code == 2
    message = one_line(refused.output)
    assert "already holds a complete result of `bayesdrive fit`" in message
    assert "seed: 1 there, 2 here" in message and "--force" in message
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    previous = os.umask(0o022)
    try:
        forced = runner.invoke(app, [*fit_args(data_dir, out, 2), "--force"])
    finally:
        os.umask(previous)
    assert forced.exit_code == 0, forced.output
    assert_complete(out, 2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit"]
    # Files respect the umask (mkstemp alone gives 0600).
    assert {(p.stat().st_mode & 0o777) for p in out.iterdir()} == {0o644}


@pytest.mark.realdata
def test_a_partial_folder_resumes_with_the_same_arguments_only(data_dir, tmp_path, monkeypatch):
    out = tmp_path / "fit"

    def killed(*_args, **_kwargs):
        raise SystemExit(137)

    # What SIGKILL leaves while result.nc is written: no clean-up runs.
    with monkeypatch.context() as patch:
        patch.setattr(output, "save_result", killed)  # fit imports it when it runs
        patch.setattr(ResultsFolder, "discard", lambda self: None)
        runner.invoke(app, fit_args(data_dir, out, 1))
    staging = staging_path(out)
    assert not out.exists() and (staging / "summary.json").exists()
    assert json.loads((staging / MANIFEST).read_text())["complete"] is False

    other = runner.invoke(app, fit_args(data_dir, out, 2))
    assert other.exit_code == 2
    message = one_line(other.output)
    assert "holds a partial result with other settings (seed: 1 there, 2 here)" in message
    assert (staging / "summary.json").exists()  # refused, not touched

    resumed = runner.invoke(app, fit_args(data_dir, out, 1))
    assert resumed.exit_code == 0, resumed.output
    assert "an interrupted run with the same arguments" in one_line(resumed.stderr)
    assert_complete(out, 1)
    assert not staging.exists()


def test_out_naming_a_file_or_an_unwritable_place_fails_before_any_work(tmp_path):
    a_file = tmp_path / "taken.txt"
    a_file.write_text("mine\n")
    # DATA does not exist either: the --out error comes first, before anything is read.
    for out, words in (
        (a_file, f"--out {a_file} is a file, not a folder"),
        (a_file / "sub", f"cannot write --out {a_file / 'sub'}: {a_file} is a file, not a folder"),
    ):
        run = runner.invoke(app, ["fit", str(tmp_path / "absent.csv"), "--out", str(out)])
        assert run.exit_code == 2
        assert run.output.strip().splitlines() == [f"error: {words}"]
    assert a_file.read_text() == "mine\n"
    folder_json = runner.invoke(
        app, ["fit", str(tmp_path / "absent.csv"), "--out", str(tmp_path / "r"), "--json", "."]
    )
    assert folder_json.exit_code == 2 and "--json . is a folder" in one_line(folder_json.output)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken.txt"]


def test_a_folder_not_written_by_a_command_is_never_replaced(tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep\n")
    with pytest.raises(OutputError, match=r"no manifest\.json"):
        open_results(tmp_path / "mine", "fit", {"seed": 1}, force=True)
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep\n"


def test_a_run_of_wider_scope_extends_a_complete_folder_and_nothing_else(tmp_path):
    out = tmp_path / "r"
    with open_results(out, "reproduce", {"quick": True, "full": False}, force=False) as first:
        write_text_atomic(first.path / "main.txt", "main\n")
        first.commit()
    old_inode = (out / "main.txt").stat().st_ino
    wider = {"quick": True, "full": True}
    # Only the folder of the run it names is extended: other sizes are refused as before.
    with pytest.raises(OutputError, match=r"other settings \(full: False there, True here"):
        open_results(out, "reproduce", wider, force=False, extends={"quick": False, "full": False})
    with open_results(
        out, "reproduce", wider, force=False, resumable=True, extends={"quick": True, "full": False}
    ) as grown:
        # The finished files are there to reuse, as links the new run never writes through.
        assert (grown.path / "main.txt").stat().st_ino == old_inode
        write_text_atomic(grown.path / "held_out.txt", "more\n")
        # The old folder stays whole until the commit.
        assert not (out / "held_out.txt").exists()
        grown.commit()
    assert sorted(p.name for p in out.iterdir()) == sorted([MANIFEST, "held_out.txt", "main.txt"])
    assert json.loads((out / MANIFEST).read_text())["arguments"] == wider
    # The folder is now the wider run's: extending it again is refused like any complete result.
    with pytest.raises(OutputError, match="of the same settings"):
        open_results(out, "reproduce", wider, force=False, extends={"quick": True, "full": False})


def test_a_kill_between_the_two_renames_of_a_replacement_is_repaired(tmp_path):
    out = tmp_path / "r"
    with open_results(out, "sim", {"seed": 1}, force=False) as first:
        write_text_atomic(first.path / "a.txt", "one\n")
        first.commit()
    # The state between the renames: the old folder moved aside, the new one not yet in place.
    with open_results(out, "sim", {"seed": 2}, force=True) as second:
        write_text_atomic(second.path / "a.txt", "two\n")
    os.rename(out, tmp_path / ".r.replaced")
    again = open_results(out, "sim", {"seed": 1}, force=True)
    assert (out / "a.txt").read_text() == "one\n"  # the old complete result is back
    assert not (tmp_path / ".r.replaced").exists()
    again.discard()
    # A staging folder whose manifest was never written is a run that never started.
    fresh = tmp_path / "s"
    staging_path(fresh).mkdir()
    (staging_path(fresh) / "junk").write_text("x")
    with open_results(fresh, "sim", {"seed": 1}, force=False) as third:
        assert not third.resumed and list(third.path.iterdir()) == [third.path / MANIFEST]


@pytest.mark.parametrize("umask", [0o022, 0o027])
def test_atomic_writes_respect_the_umask(tmp_path, umask):
    previous = os.umask(umask)
    try:
        write_text_atomic(tmp_path / "x.json", "{}\n")
    finally:
        os.umask(previous)
    assert (tmp_path / "x.json").stat().st_mode & 0o777 == 0o666 & ~umask


JSON_COMMANDS = (
    ["fit", "absent.csv", "--out", "r"],
    ["diagnose", "result.nc"],
    ["sbc", "--engine", "smc", "--seed", "1", "--out", "r"],
    ["simulate", "paper_congested", "--seed", "1", "--out", "r"],
    ["criticize", "absent.csv"],
    ["evaluate", "absent.csv", "--model", "cv"],
    ["data", "list"],
    ["data", "info", "absent.csv"],
    ["data", "verify", "ngsim_i80_chains"],
    ["data", "fetch", "ngsim_i80_chains"],
    ["validate", "sumo", "result.nc", "absent.csv", "--out", "r"],
)


def test_every_command_refuses_to_replace_a_json_file_without_force(tmp_path, monkeypatch):
    """One rule for every command that takes --json, checked before any work (no data exists
    here to read or fetch)."""
    names = {name for command in json_commands() for name in command}
    monkeypatch.chdir(tmp_path)
    (tmp_path / "result.nc").write_bytes(b"")  # diagnose checks its inputs exist first
    taken = tmp_path / "taken.json"
    taken.write_text("mine\n")
    assert {tuple(a for a in args if a in names) for args in JSON_COMMANDS} == json_commands()
    for args in JSON_COMMANDS:
        run = runner.invoke(app, [*args, "--json", str(taken)])
        assert run.exit_code == 2, (args, run.output)
        assert one_line(run.output) == f"error: --json {taken} exists; use --force to replace it"
    assert taken.read_text() == "mine\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.nc", "taken.json"]


@pytest.mark.realdata
def test_force_replaces_a_json_file(data_dir, tmp_path):
    taken = tmp_path / "taken.json"
    taken.write_text("mine\n")
    args = ["data", "info", str(data_dir / CHAIN), "--json", str(taken)]
    assert runner.invoke(app, args).exit_code == 2 and taken.read_text() == "mine\n"
    forced = runner.invoke(app, [*args, "--force"])
    assert forced.exit_code == 0, forced.output
    assert json.loads(taken.read_text())["source"].endswith(Path(CHAIN).name)


def json_commands() -> set[tuple[str, ...]]:
    """Every command (group, subcommand) that takes --json, as the CLI registers them."""
    found = set()
    for name in COMMANDS:
        command = load_command(name)
        subcommands = getattr(command, "commands", {name: command})
        for sub, leaf in subcommands.items():
            if any(p.name == "json_out" for p in leaf.params):
                found.add((name,) if sub == name else (name, sub))
    return found


def test_simulate_refuses_a_complete_folder_without_force(tmp_path):
    args = ["simulate", "paper_congested", "--vehicles", "2", "--duration", "1", "--scenes", "2"]
    out = tmp_path / "scenes"
    first = runner.invoke(app, [*args, "--seed", "1", "--out", str(out)])
    assert first.exit_code == 0, first.output
    again = runner.invoke(app, [*args, "--seed", "1", "--out", str(out)])
    assert again.exit_code == 2
    assert "already holds a complete result of `bayesdrive simulate` of the same settings" in (
        one_line(again.output)
    )
    forced = runner.invoke(app, [*args, "--seed", "2", "--out", str(out), "--force"])
    assert forced.exit_code == 0, forced.output
    assert json.loads((out / "summary.json").read_text())["seed"] == 2
    assert json.loads((out / MANIFEST).read_text())["files"] == sorted(
        ["scenes.nc", "speed_gap_kde.png", "summary.json", "sweep.png"]
    )


def test_a_second_run_into_the_same_folder_is_refused_while_the_first_is_alive(tmp_path):
    out = tmp_path / "r"
    with open_results(out, "sim", {"seed": 1}, force=False, resumable=True) as first:
        with pytest.raises(OutputError, match="being written by another run now"):
            open_results(out, "sim", {"seed": 1}, force=True)
        assert (first.path / MANIFEST).exists()  # --force did not discard a live run's folder
    # Once the first run is gone (here: left without a commit), its folder resumes.
    with open_results(out, "sim", {"seed": 1}, force=False, resumable=True) as second:
        assert second.resumed


SIGNAL_LANDS = {
    # JAX's garbage-collector callback is where a real fit's SIGTERM was lost: Python ignores an
    # error raised in such a callback, so the command went on and finished.
    "in_a_gc_callback": """
def lands():
    def callback(phase, info):
        if phase == "start":
            gc.callbacks.remove(callback)  # once: later collections come on the way out
            os.kill(os.getpid(), signal.SIGTERM)
    gc.callbacks.append(callback)
    gc.collect()
""",
    # Code that wraps every error in one of its own turned the exit into an error (exit 1).
    "under_code_that_converts_errors": """
def lands():
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(1)
    except BaseException as error:
        raise RuntimeError("wrapped") from error
""",
}


@pytest.mark.parametrize("where", list(SIGNAL_LANDS))
def test_sigterm_exits_143_wherever_its_handler_runs(where, tmp_path):
    script = (
        "import gc, os, signal, sys, time\n"
        "from bayesdrive.cli.common import exit_cleanly_on_sigterm, results_command\n"
        + SIGNAL_LANDS[where]
        + "@results_command\n"
        "def command():\n"
        "    exit_cleanly_on_sigterm()\n"
        "    lands()\n"
        "    time.sleep(2)\n"
        "    print('went on after SIGTERM')\n"
        "command()\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script],
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert "went on after SIGTERM" not in done.stdout, done.stderr
    assert done.returncode == 128 + signal.SIGTERM, done.stderr
