"""`bayesdrive evaluate` through typer's CliRunner on a small real scene set."""

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from bayesdrive.cli.main import app
from bayesdrive.data import registry
from bayesdrive.data.views import SPLIT_RULE, follower_arrays
from bayesdrive.inference.output import build_tree, save_result
from bayesdrive.simulation import evaluation

runner = CliRunner()

# Two overlapping NGSIM chain files: after deduplication one platoon of 7 vehicles.
CHAIN_FILES = ("1_11_24_44_55_54.csv", "11_24_44_55_54_59.csv")
SMALL = ["--horizon", "2", "--vehicles-per-scenario", "3", "--rollouts", "2", "--seed", "5"]


def one_line(text: str) -> str:
    """Rich wraps long lines at the console width; compare messages with whitespace collapsed."""
    return " ".join(text.split())


@pytest.fixture(scope="module")
def scene_dir(data_dir, tmp_path_factory):
    folder = tmp_path_factory.mktemp("chains")
    for name in CHAIN_FILES:
        shutil.copy(data_dir / "ngsim_i80_chains" / name, folder / name)
    return folder


def evaluate(*args: str):
    return runner.invoke(app, ["evaluate", *map(str, args)])


@pytest.mark.realdata
def test_json_holds_the_metrics_the_seed_and_the_split(scene_dir):
    result = evaluate(scene_dir, "--model", "idm-nls", *SMALL, "--json", "-")
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)  # nothing but the JSON on stdout
    for key in ("model", "scenarios", "vehicles", "collisions", "hard_braking", "seed"):
        assert key in out
    assert out["model"] == "idm-nls"
    assert (out["seed"], out["horizon_s"], out["rollouts"]) == (5, 2.0, 2)
    assert out["split_rule"] == SPLIT_RULE
    assert out["scenarios"] == len(out["by_scenario"]) == out["scenario_set"]["scenarios"] > 0
    assert out["vehicles"] == 3 * out["scenarios"]
    for metric in ("rmse_position_m", "rmse_speed_mps"):
        summary = out[metric]
        assert set(summary) == {"mean", "sd", "by_step"}
        assert len(summary["by_step"]["mean"]) == 21  # steps 0..20 of a 2 s horizon
        assert summary["by_step"]["mean"][-1] == pytest.approx(summary["mean"])
        finals = [s[metric] for s in out["by_scenario"]]
        assert summary["mean"] == pytest.approx(np.mean(finals))
    assert set(out["collisions"]) >= {"total", "fraction"}
    assert "total" in out["hard_braking"]

    again = evaluate(scene_dir, "--model", "idm-nls", *SMALL, "--json", "-")
    assert json.loads(again.stdout) == out  # same seed, same numbers


@pytest.mark.realdata
def test_the_table_is_printed_without_json(scene_dir):
    result = evaluate(scene_dir, "--model", "cv", *SMALL)
    assert result.exit_code == 0, result.output
    text = one_line(result.stdout)
    assert "RMSE position at the horizon" in text and "collisions" in text


def posterior_file(traj, *, vehicles=None, **meta_changes):
    """A result.nc as `bayesdrive fit` writes it: IDM tau and v_des draws per vehicle."""
    arrays = follower_arrays(traj, window="fit", vehicle_ids=vehicles)
    num_vehicles, num_steps = arrays.mask.shape
    rng = np.random.default_rng(0)
    posterior = {
        "v_des": rng.uniform(10.0, 20.0, (1, 50, num_vehicles)),
        "tau": rng.uniform(0.8, 1.6, (1, 50, num_vehicles)),
    }
    metadata = {
        "engine": "test",
        "model": "idm",
        "params": ["v_des", "tau"],
        "fixed": {"sigma": 0.2},
        "seed": 0,
        "data_source": traj.source,
        "window": "fit",
        "num_particles": 50,
        "flagged_samples": 0,
        **meta_changes,
    }
    tree = build_tree(
        posterior=posterior,
        sample_stats={},
        log_likelihood=np.zeros((1, 50, num_vehicles, num_steps)),
        arrays=arrays,
        metadata=metadata,
    )
    return tree


@pytest.fixture
def results(monkeypatch, tmp_path):
    """Result trees by path, served to the CLI in place of reading netCDF: the file round trip is
    output.py's to test (and needs h5py, which this environment may lack)."""
    trees = {}

    def save(tree, name: str):
        path = tmp_path / name
        trees[path] = tree
        return path

    monkeypatch.setattr(evaluation, "load_result", lambda path: trees[Path(path)])
    return save


@pytest.mark.realdata
def test_a_posterior_from_the_same_split_runs_and_others_are_refused(scene_dir, results):
    traj = registry.load(scene_dir)
    good = results(posterior_file(traj), "good.nc")
    result = evaluate(scene_dir, "--model", "idm", "--posterior", good, *SMALL, "--json", "-")
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)
    assert out["model"] == "idm" and out["policy_details"]["fixed"] == {"sigma": 0.2}
    # The same folder spelled as a relative path is the same data source.
    relative = results(posterior_file(traj, data_source=os.path.relpath(scene_dir)), "rel.nc")
    accepted = evaluate(scene_dir, "--model", "idm", "--posterior", relative, *SMALL)
    assert accepted.exit_code == 0, accepted.output

    refusals = {
        "window": (posterior_file(traj, window="all"), "fitted on the 'all' window"),
        "source": (posterior_file(traj, data_source="elsewhere"), "fitted on 'elsewhere'"),
    }
    other_rule = posterior_file(traj)
    other_rule.attrs["split_rule"] = "first 50% of each vehicle"
    refusals["rule"] = (other_rule, "split rule 'first 50% of each vehicle'")
    for name, (tree, message) in refusals.items():
        path = results(tree, f"{name}.nc")
        refused = evaluate(scene_dir, "--model", "idm", "--posterior", path, *SMALL)
        assert refused.exit_code == 2, name
        assert "refusing the posterior" in one_line(refused.stderr)
        assert message in one_line(refused.stderr), name

    wrong_model = evaluate(scene_dir, "--model", "cidm", "--posterior", good, *SMALL)
    assert wrong_model.exit_code == 2
    assert "not --model 'cidm'" in one_line(wrong_model.stderr)


@pytest.mark.realdata
def test_a_posterior_read_from_its_netcdf_file(scene_dir, tmp_path):
    pytest.importorskip("h5py", reason="h5netcdf needs h5py to read or write netCDF4 files")
    path = save_result(posterior_file(registry.load(scene_dir)), tmp_path / "result.nc")
    result = evaluate(scene_dir, "--model", "idm", "--posterior", path, *SMALL, "--json", "-")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["policy_details"]["result"] == str(path)


@pytest.mark.realdata
def test_a_partial_posterior_scores_the_fitted_vehicles_and_names_the_skipped(scene_dir, results):
    traj = registry.load(scene_dir)
    scenes = evaluation.evaluation_scenarios(traj, 2.0, 3)
    assert len(scenes.scenarios) > 1
    dropped = scenes.scenarios[-1].simulated_ids[-1]
    lacking = [s for s in scenes.scenarios if dropped in s.simulated_ids]
    assert len(lacking) < len(scenes.scenarios)
    kept = [v for v in traj.vehicle_ids if v != dropped]
    path = results(posterior_file(traj, vehicles=kept), "partial.nc")
    result = evaluate(scene_dir, "--model", "idm", "--posterior", path, *SMALL, "--json", "-")
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)
    assert out["skipped"]["vehicles"] == [dropped]
    assert out["skipped"]["scenarios"] == len(lacking)
    assert out["scenarios"] == len(scenes.scenarios) - len(lacking)
    scored = {s.scenario_id for s in scenes.scenarios if s not in lacking}
    assert {s["scenario"] for s in out["by_scenario"]} == scored
    printed = evaluate(scene_dir, "--model", "idm", "--posterior", path, *SMALL)
    assert f"skipped {len(lacking)} scenario(s)" in one_line(printed.stdout)
    assert dropped in printed.stdout

    # One fitted vehicle completes no 3-vehicle scenario: an error, not an empty score.
    nothing = results(posterior_file(traj, vehicles=scenes.simulated_ids[:1]), "none.nc")
    refused = evaluate(scene_dir, "--model", "idm", "--posterior", nothing, *SMALL)
    assert refused.exit_code == 2
    assert "every one of the" in one_line(refused.stderr)


@pytest.mark.realdata
def test_bad_requests_end_with_one_error_line(scene_dir, monkeypatch):
    unknown = evaluate(scene_dir, "--model", "gail", *SMALL)
    assert unknown.exit_code == 2 and "unknown model 'gail'" in one_line(unknown.stderr)
    too_big = evaluate(scene_dir, "--model", "cv", "--vehicles-per-scenario", "9", "--horizon", "2")
    assert too_big.exit_code == 2
    assert "scenarios per size the data allows: 1:" in one_line(too_big.stderr)
    merge_only = evaluate(scene_dir, "--model", "cidm-c1", *SMALL)
    assert merge_only.exit_code == 2 and "no merge episodes" in one_line(merge_only.stderr)
    # Data loaded as held out: nothing may be fitted on it (held-out files themselves are not
    # read in tests, so the loader's verdict is stubbed on this fitting data).
    real_load = evaluation.evaluation_data
    monkeypatch.setattr(evaluation, "evaluation_data", lambda *a: (real_load(*a)[0], True))
    held_out = evaluate(scene_dir, "--model", "blackbox", *SMALL)
    assert held_out.exit_code == 2 and "held out for evaluation only" in one_line(held_out.stderr)


def test_an_error_message_is_printed_as_written(monkeypatch):
    # Brackets in a message (a list of ids, say) reach the user once escaped, not twice.
    def refuse(*args, **kwargs):
        raise ValueError("vehicles ['a', 'b'] have no leader [fit window]")

    monkeypatch.setattr(evaluation, "evaluate", refuse)
    result = evaluate("any.csv", "--model", "cv")
    assert result.exit_code == 2
    assert "vehicles ['a', 'b'] have no leader [fit window]" in one_line(result.output)
