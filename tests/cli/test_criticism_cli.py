"""``bayesdrive criticize`` end to end on a small generated file: JSON, pictures, exit codes."""

from __future__ import annotations

import json

import pytest
import typer
from typer.testing import CliRunner

from bayesdrive.cli.criticize_cmd import criticize_command
from bayesdrive.criticism.criticize import POWERED_VEHICLES, criticized_series, power_warning
from bayesdrive.data.readers import read
from bayesdrive.data.views import follower_arrays
from bayesdrive.inference.core.output import load_result, metadata
from bayesdrive.inference.fit import first_vehicles
from trafficgen import DETECTION_SCENARIO, generate

app = typer.Typer()
app.command()(criticize_command)

# The file's format, the seed and the sampler of the tests that criticize ``small_file``: one
# setting, so a later test reuses the fits an earlier one compiled.
CRITICIZE_SMALL = (
    *("--format", "ngsim_raw", "--seed", "3"),
    *("--particles", "64", "--unmoved-tolerance", "0.05"),
)


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


@pytest.mark.extended
def test_json_on_stdout_and_pictures(small_file, tmp_path):
    """--json - writes only JSON on stdout; --out writes the check pictures and the final model
    (a result file that loads, of the model the JSON names, with its model card)."""
    out = tmp_path / "figures"
    result = CliRunner().invoke(
        app,
        [
            str(small_file),
            *CRITICIZE_SMALL,
            "--rollouts",
            "4",
            "--causes",
            "reaction_delay",
            "--final-particles",
            "128",
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
    assert report["verdict"] in ("reaction_delay", "none") or report["verdict"].startswith(
        "unexplained: "
    )
    assert [c["name"] for c in report["causes"]] == ["reaction_delay"]
    first = report["rounds"][0]
    assert first["causes"] == report["causes"]
    # Every round records its misfit, named cause, both gains and the adoption with its reason.
    named = first["named"]
    assert named == (None if report["verdict"] != "reaction_delay" else "reaction_delay")
    assert (first["one_step_gain"] is None) == (named is None)
    assert (first["forecast_gain"] is None) == (named is None)
    assert first["adopted"] in (True, False) and first["adoption"].startswith(
        ("adopted: ", "not adopted: ", "no cause named")
    )
    assert all(m["p_value"] <= 0.05 for m in first["misfit"])
    expected_model = "idm+reaction_delay" if first["adopted"] else "idm"
    assert report["model"] == expected_model
    assert report["adopted"] == expected_model.split("+")[1:]
    names = {p.name for p in out.iterdir()}
    assert {
        "calibration.png",
        "correlations.png",
        "causes.png",
        "multistep.png",
        "screening.png",
        "final_model.nc",
        "final_model.md",
    } <= names
    final = metadata(load_result(out / "final_model.nc"))
    assert final["model"] == expected_model and final["engine"] == "smc"
    assert final["num_vehicles"] == report["data"]["vehicles"]
    assert f"# {expected_model}" in (out / "final_model.md").read_text()
    assert all(p.stat().st_size > 10_000 for p in out.glob("*.png"))
    assert json.loads((out / "manifest.json").read_text())["files"] == sorted(
        names - {"manifest.json"}
    )


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


@pytest.mark.extended
def test_vehicles_are_counted_as_fit_counts_them_and_few_of_them_draw_a_warning(small_file):
    """--vehicles 2 criticizes the 2 vehicles `fit --vehicles 2` fits, and says the checks lack
    power with so few (the detection study's vehicle count draws no such warning)."""
    result = CliRunner().invoke(
        app,
        [
            str(small_file),
            *CRITICIZE_SMALL,
            *("--rollouts", "0", "--causes", "reaction_delay", "--vehicles", "2"),
        ],
    )
    assert result.exit_code == 0, result.output
    text = " ".join(result.stdout.split())
    assert "Low power: only 2 vehicle(s) criticized" in text
    assert f"shown with {POWERED_VEHICLES} vehicles" in text

    traj = read(small_file, format="ngsim_raw")
    fitted = first_vehicles(follower_arrays(traj, window="fit"), 2).vehicle_ids
    assert criticized_series(traj, 2).vehicle_ids == fitted
    assert power_warning(POWERED_VEHICLES) is None
    assert "undefined with one vehicle" in power_warning(1)


def test_the_power_threshold_is_the_detection_studys_vehicle_count():
    assert DETECTION_SCENARIO["platoons"] * DETECTION_SCENARIO["followers"] == POWERED_VEHICLES
