"""`bayesdrive data ...` through typer's CliRunner."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from test_fetch import no_real_network, serve  # noqa: F401  (autouse guard: loopback only)
from typer.testing import CliRunner

from bayesdrive.cli.main import app
from bayesdrive.data.registry import DATASETS, HOLDOUT

runner = CliRunner()
ROOT = Path(__file__).resolve().parents[2]


def one_line(text: str) -> str:
    """Rich wraps long lines at the console width; compare messages with whitespace collapsed."""
    return " ".join(text.split())


def test_list_shows_every_data_set_with_its_role(tmp_path):
    result = runner.invoke(
        app, ["data", "list", "--data-dir", str(tmp_path), "--holdout-dir", str(tmp_path)]
    )
    assert result.exit_code == 0, result.output
    for name in (*DATASETS, *HOLDOUT):
        assert name in result.stdout


def test_list_json_tells_present_from_absent(tmp_path):
    result = runner.invoke(
        app,
        [
            "data",
            "list",
            "--data-dir",
            str(tmp_path),
            "--holdout-dir",
            str(tmp_path),
            "--json",
            "-",
        ],
    )
    assert result.exit_code == 0, result.output
    rows = {row["name"]: row for row in json.loads(result.stdout)}
    assert set(rows) == set(DATASETS) | set(HOLDOUT)
    assert {row["present"] for row in rows.values()} == {"no"}
    assert {rows[n]["role"] for n in HOLDOUT} == {"holdout"}


@pytest.mark.realdata
def test_list_verifies_what_is_present(data_dir, holdout_dir):
    result = runner.invoke(
        app,
        [
            "data",
            "list",
            "--data-dir",
            str(data_dir),
            "--holdout-dir",
            str(holdout_dir),
            "--json",
            "-",
        ],
    )
    assert result.exit_code == 0, result.output
    assert {row["present"] for row in json.loads(result.stdout)} == {"yes"}


@pytest.mark.realdata
def test_fetch_and_verify_through_the_cli(data_dir, tmp_path):
    dest = tmp_path / "data"
    with serve(data_dir) as url:
        fetched = runner.invoke(
            app,
            ["data", "fetch", "interaction_fixture", "--data-dir", str(dest), "--mirror", url],
        )
    assert fetched.exit_code == 0, fetched.output
    assert "verified" in fetched.stdout
    checked = runner.invoke(
        app, ["data", "verify", "interaction_fixture", "--data-dir", str(dest), "--json", "-"]
    )
    assert checked.exit_code == 0, checked.output
    assert json.loads(checked.stdout)["ok"] is True

    (dest / "interaction_fixture" / "LICENSE.txt").write_text("changed\n")
    changed = runner.invoke(app, ["data", "verify", "interaction_fixture", "--data-dir", str(dest)])
    assert changed.exit_code == 1
    assert "LICENSE.txt: size" in changed.stdout


@pytest.mark.realdata
def test_fetch_from_a_corrupted_mirror_exits_2_with_the_checksum_message(data_dir, tmp_path):
    mirror = tmp_path / "mirror"
    shutil.copytree(Path(data_dir) / "interaction_fixture", mirror / "interaction_fixture")
    tracks = mirror / "interaction_fixture" / "vehicle_tracks_000.csv"
    tracks.write_bytes(tracks.read_bytes().replace(b"10", b"11", 1))
    with serve(mirror) as url:
        result = runner.invoke(
            app,
            [
                "data",
                "fetch",
                "interaction_fixture",
                "--data-dir",
                str(tmp_path / "d"),
                "--mirror",
                url,
            ],
        )
    assert result.exit_code == 2
    assert "checksum mismatch" in one_line(result.stderr)
    assert isinstance(result.exception, SystemExit)  # a clean exit, not an escaped exception
    assert not (tmp_path / "d").exists()


def test_fetch_of_an_unknown_name_exits_2(tmp_path):
    result = runner.invoke(app, ["data", "fetch", "nope", "--data-dir", str(tmp_path)])
    assert result.exit_code == 2
    assert "unknown data set 'nope'" in one_line(result.stderr)


# ---- info ---------------------------------------------------------------------------------------


@pytest.mark.realdata
def test_info_json_on_stdout_is_pure_json(data_dir):
    result = runner.invoke(
        app, ["data", "info", "ngsim_i80_chains", "--data-dir", str(data_dir), "--json", "-"]
    )
    assert result.exit_code == 0, result.stderr
    info = json.loads(result.stdout)  # nothing but the JSON document on stdout
    # The data set's documented figures (shared/data/README.md): 75 chains, 210 vehicles, 10 Hz.
    assert info["format"] == "ngsim_chains"
    assert info["scenes"] == 75
    assert info["vehicles"] == 210
    assert info["dt_s"] == pytest.approx(0.1)
    for key in ("time_steps", "duration_s", "leader_follower_pairs"):
        assert info[key] > 0
    assert set(info["speed_mps"]) == {"min", "median", "max"}
    assert set(info["gap_m"]) == {"min", "median"}


@pytest.mark.realdata
def test_info_accepts_a_held_out_name(holdout_dir):
    result = runner.invoke(
        app, ["data", "info", "acc_platoon_fhwa", "--data-dir", str(holdout_dir), "--json", "-"]
    )
    assert result.exit_code == 0, result.stderr
    assert json.loads(result.stdout)["source"] == "acc_platoon_fhwa"


def test_info_on_a_bad_file_exits_2_with_the_message_and_no_traceback(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("what,is,this\n1,2,3\n")
    result = runner.invoke(app, ["data", "info", str(bad)])
    assert result.exit_code == 2
    message = one_line(result.stderr)
    assert message.startswith("error:") and "bad.csv" in message
    assert "cannot tell the format" in message
    assert "Traceback" not in result.output
    assert isinstance(result.exception, SystemExit)  # a clean exit, not an escaped exception


def test_info_on_a_missing_data_set_names_the_fetch_command(tmp_path):
    result = runner.invoke(app, ["data", "info", "ngsim_i80_chains", "--data-dir", str(tmp_path)])
    assert result.exit_code == 2
    assert "bayesdrive data fetch ngsim_i80_chains" in one_line(result.stderr)


def write_two_cars_in_feet(path: Path, leader_gap_ft: float = 60.0) -> None:
    """Car 1 follows car 2 at 30 ft/s for 3 s; 'space' is front to front; cars are 15 ft long."""
    lines = ["ID,time,pos,speed,lead,space,len"]
    for k in range(31):
        t = round(0.1 * k, 1)
        lines.append(f"1,{t},{3.0 * k:.1f},30,2,{leader_gap_ft},15")
    for k in range(31):
        t = round(0.1 * k, 1)
        lines.append(f"2,{t},{leader_gap_ft + 3.0 * k:.1f},30,0,,15")
    path.write_text("\n".join(lines) + "\n")


COLUMN_MAP = "vehicle_id=ID,t=time,x=pos,v=speed,leader_id=lead,gap=space,length=len"


@pytest.mark.parametrize(
    ("headway", "gap_ft"),
    [("front", 60.0 - 15.0), ("bumper", 60.0)],  # front-to-front minus the leader's length
)
def test_info_passes_the_column_map_units_and_headway_to_the_reader(tmp_path, headway, gap_ft):
    table = tmp_path / "cars.csv"
    write_two_cars_in_feet(table)
    options = ["--columns", COLUMN_MAP, "--units", "ft", "--headway", headway]
    result = runner.invoke(app, ["data", "info", str(table), *options, "--json", "-"])
    assert result.exit_code == 0, result.stderr
    info = json.loads(result.stdout)
    assert info["format"] == "columns"
    assert info["vehicles"] == 2 and info["leader_follower_pairs"] == 1
    assert info["speed_mps"]["median"] == pytest.approx(30 * 0.3048)
    assert info["gap_m"]["median"] == pytest.approx(gap_ft * 0.3048)


def test_info_strict_refuses_flagged_data(tmp_path):
    table = tmp_path / "cars.csv"
    write_two_cars_in_feet(table, leader_gap_ft=10.0)  # 10 ft front to front: cars overlap
    args = ["data", "info", str(table), "--columns", COLUMN_MAP, "--units", "ft"]
    lenient = runner.invoke(app, [*args, "--headway", "front", "--json", "-"])
    assert lenient.exit_code == 0, lenient.stderr
    assert json.loads(lenient.stdout)["flags"] == {"negative_gap": 31}
    strict = runner.invoke(app, [*args, "--headway", "front", "--strict"])
    assert strict.exit_code == 2
    assert "strict mode refuses flagged data" in one_line(strict.stderr)


def test_info_refuses_column_map_options_for_another_reader(tmp_path):
    table = tmp_path / "cars.csv"
    write_two_cars_in_feet(table)
    result = runner.invoke(
        app, ["data", "info", str(table), "--format", "openacc", "--units", "ft"]
    )
    assert result.exit_code == 2
    assert "options of --format columns, not of openacc" in one_line(result.stderr)


def test_info_rejects_a_malformed_column_map(tmp_path):
    table = tmp_path / "cars.csv"
    write_two_cars_in_feet(table)
    result = runner.invoke(app, ["data", "info", str(table), "--columns", "vehicle_id"])
    assert result.exit_code == 2
    assert "is not SCHEMA=FILE_COLUMN" in one_line(result.stderr)


@pytest.mark.realdata
@pytest.mark.parametrize("verbose", [False, True])
def test_flagged_sample_notes_are_logged_at_verbose_only(data_dir, verbose):
    """The chain file holds negative bumper gaps: the reader's note about flagging them is a log
    line for -v, not a warning on every run (the counts stay in the command's own output)."""
    chain = data_dir / "ngsim_i80_chains" / "124_136_140_146_162_164.csv"
    args = [*(["-v"] if verbose else []), "data", "info", str(chain)]
    done = subprocess.run(
        [sys.executable, "-m", "bayesdrive.cli.main", *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert done.returncode == 0, done.stderr
    assert ("sample(s) flagged (negative_gap)" in done.stderr) == verbose
    assert "flagged (negative_gap)" in " ".join(done.stdout.split())
