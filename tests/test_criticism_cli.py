"""``bayesdrive criticize`` end to end on a small generated file: JSON, pictures, exit codes."""

from __future__ import annotations

import json

import pytest
import typer
from typer.testing import CliRunner

from bayesdrive.cli.criticize_cmd import criticize_command
from trafficgen import generate

app = typer.Typer()
app.command()(criticize_command)


@pytest.fixture(scope="module")
def small_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "delay.csv"
    generate(
        3,
        path,
        {"perception_delay": (0.4, 0.7)},
        platoons=1,
        followers=4,
        duration_s=30.0,
        cut_ins=0,
    )
    return path


def test_json_on_stdout_and_pictures(small_file, tmp_path):
    """--json - writes only JSON on stdout; --out writes the check pictures."""
    out = tmp_path / "figures"
    result = CliRunner().invoke(
        app,
        [
            str(small_file),
            "--format",
            "ngsim_raw",
            "--seed",
            "3",
            "--particles",
            "64",
            "--unmoved-tolerance",
            "0.05",
            "--rollouts",
            "4",
            "--causes",
            "reaction_delay",
            "--out",
            str(out),
            "--json",
            "-",
        ],
    )
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["seed"] == 3
    assert report["settings"]["num_particles"] == 64
    assert report["settings"]["unmoved_tolerance"] == 0.05
    assert report["verdict"] in ("reaction_delay", "none")
    assert [c["name"] for c in report["causes"]] == ["reaction_delay"]
    names = {p.name for p in out.iterdir()}
    assert {
        "calibration.png",
        "correlations.png",
        "causes.png",
        "multistep.png",
        "screening.png",
    } <= names
    assert all(p.stat().st_size > 10_000 for p in out.iterdir())


def test_bad_input_is_a_one_line_error_with_exit_code_2(tmp_path, small_file):
    missing = CliRunner().invoke(app, [str(tmp_path / "nothing_here.csv")])
    assert missing.exit_code == 2
    unknown = CliRunner().invoke(
        app, [str(small_file), "--format", "ngsim_raw", "--causes", "bad_weather"]
    )
    assert unknown.exit_code == 2
    assert "bad_weather" in unknown.output
    tolerance = CliRunner().invoke(
        app, [str(small_file), "--format", "ngsim_raw", "--unmoved-tolerance", "1.5"]
    )
    assert tolerance.exit_code == 2
    assert "--unmoved-tolerance" in tolerance.output
