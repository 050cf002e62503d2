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
from bayesdrive.data.errors import DataError
from bayesdrive.data.views import SPLIT_RULE, follower_arrays
from bayesdrive.inference.core.output import build_tree, save_result
from bayesdrive.simulation import evaluation
from bayesdrive.simulation.scenarios import platoon_scenarios

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
def test_bad_requests_end_with_one_error_line(scene_dir):
    unknown = evaluate(scene_dir, "--model", "gail", *SMALL)
    assert unknown.exit_code == 2 and "unknown model 'gail'" in one_line(unknown.stderr)
    too_big = evaluate(scene_dir, "--model", "cv", "--vehicles-per-scenario", "9", "--horizon", "2")
    assert too_big.exit_code == 2
    assert "scenarios per size the data allows: 1:" in one_line(too_big.stderr)
    merge_only = evaluate(scene_dir, "--model", "cidm-c1", *SMALL)
    assert merge_only.exit_code == 2 and "no merge episodes" in one_line(merge_only.stderr)


@pytest.mark.realdata
def test_a_baseline_that_fits_follows_the_held_out_protocol_on_held_out_data(
    scene_dir, monkeypatch, caplog
):
    """Fitted on the fitting windows with its documented settings, scored on the held-out
    windows, with the note that nothing may be tuned on the data logged (the loader's held-out
    verdict is stubbed on this fitting data: no score of a held-out set is asserted anywhere)."""
    real_load = evaluation.evaluation_data
    monkeypatch.setattr(evaluation, "evaluation_data", lambda *a: (real_load(*a)[0], True))
    with caplog.at_level("WARNING"):
        held_out = evaluate(scene_dir, "--model", "idm-lm", *SMALL, "--json", "-")
    assert held_out.exit_code == 0, held_out.output
    notes = [r.getMessage() for r in caplog.records if "held out" in r.getMessage()]
    assert len(notes) == 1 and "never choose or tune" in notes[0]
    out = json.loads(held_out.stdout)
    assert out["policy"] == "IDM fitted per vehicle by LM on its fitting window, sigma = 0"
    assert out["scenarios"] > 0 and out["skipped"] is None
    assert out["policy_details"]["fitted"] == ["v_des", "d_min", "tau", "a_max", "b_pref"]


@pytest.mark.realdata
def test_without_a_size_the_largest_the_data_allows_is_taken_and_said(scene_dir):
    args = ["--model", "cv", "--horizon", "2", "--rollouts", "1", "--seed", "5"]
    result = evaluate(scene_dir, *args, "--json", "-")
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)
    size = out["vehicles_per_scenario"]
    traj = registry.load(scene_dir)
    assert platoon_scenarios(traj, vehicles_per_scenario=size, horizon_s=2.0).scenarios
    assert not platoon_scenarios(traj, vehicles_per_scenario=size + 1, horizon_s=2.0).scenarios
    assert out["vehicles"] == size * out["scenarios"]
    assert out["scenario_size"].startswith(f"{size} vehicle(s) per scenario, the largest size")
    printed = one_line(evaluate(scene_dir, *args).stdout)
    assert f"scenario size: {size} vehicle(s) per scenario, the largest size the data" in printed
    given = evaluate(scene_dir, *args, "--vehicles-per-scenario", "1", "--json", "-")
    assert json.loads(given.stdout)["scenario_size"] is None  # said only when chosen


@pytest.mark.realdata
def test_every_held_out_set_has_a_scenario_size_or_says_why_not(holdout_dir):
    """What `bayesdrive evaluate NAME` chooses with no extra flag, on every held-out set (read
    through the readers, as evaluation reads them; nothing is scored here)."""
    for name in registry.HOLDOUT:
        traj, held_out = evaluation.evaluation_data(name, str(holdout_dir))
        assert held_out, name
        if not traj.tracks["leader_id"].notna().any():
            with pytest.raises(DataError, match="no vehicle has a recorded leader"):
                evaluation.largest_scenario_size(traj, 5.0)
            continue
        size, _ = evaluation.largest_scenario_size(traj, 5.0)
        assert evaluation.evaluation_scenarios(traj, 5.0, size).scenarios, name


def test_an_error_message_is_printed_as_written(monkeypatch):
    # Brackets in a message (a list of ids, say) reach the user once escaped, not twice.
    def refuse(*args, **kwargs):
        raise ValueError("vehicles ['a', 'b'] have no leader [fit window]")

    monkeypatch.setattr(evaluation, "evaluate", refuse)
    result = evaluate("any.csv", "--model", "cv")
    assert result.exit_code == 2
    assert "vehicles ['a', 'b'] have no leader [fit window]" in one_line(result.output)
