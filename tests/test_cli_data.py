"""`bayesdrive data ...` through typer's CliRunner."""

import json
import shutil
from pathlib import Path

import pytest
from test_fetch import no_real_network, serve  # noqa: F401  (autouse guard: loopback only)
from typer.testing import CliRunner

from bayesdrive.cli.main import app
from bayesdrive.data.registry import DATASETS, HOLDOUT

runner = CliRunner()


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
    assert result.exception is None or isinstance(result.exception, SystemExit)
    assert not (tmp_path / "d").exists()


def test_fetch_of_an_unknown_name_exits_2(tmp_path):
    result = runner.invoke(app, ["data", "fetch", "nope", "--data-dir", str(tmp_path)])
    assert result.exit_code == 2
    assert "unknown data set 'nope'" in one_line(result.stderr)
