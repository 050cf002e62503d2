"""SUMO round trip: a fitted NGSIM result's drivers, run by SUMO's own IDM behind the recorded
leaders, against bayesdrive's rollouts of the same drivers and against the data
(``bayesdrive validate sumo``, :mod:`bayesdrive.simulation.sumo_validation`).

Set-up: the committed ``models/ngsim_i80_chains_idm_smc.nc``, its first 2 fitted vehicles, their
5 s windows of the held-out part behind one recorded leader, one posterior-predictive rollout per
window (the shapes of the deterministic rollouts, so one program serves both), 50 bootstrap
resamples, seed 1. The data are the real recordings and SUMO is independent of bayesdrive, so
nothing here grades bayesdrive on its own output.

Pass: every 1-Wasserstein distance between SUMO's and bayesdrive's gap, speed and acceleration
distributions has its upper 95% bound within the module's TOLERANCE (0.05 m, 0.02 m/s,
0.02 m/s^2). Negative control: the same drivers with tau halved in SUMO must miss it (the
command runs it every time and fails without it).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from bayesdrive.cli.main import app
from bayesdrive.simulation.sumo import sumo_home

MODELS = Path(__file__).resolve().parents[2] / "models"
MODEL = MODELS / "ngsim_i80_chains_idm_smc.nc"
runner = CliRunner()


@pytest.mark.realdata
def test_exported_drivers_in_sumo_match_bayesdrives_rollouts_and_the_wrong_tau_fails(
    data_dir, tmp_path, monkeypatch
):
    try:
        sumo_home()
    except RuntimeError as error:
        if os.environ.get("CI"):
            pytest.fail(str(error))
        pytest.skip(str(error))
    monkeypatch.setenv("BAYESDRIVE_DATA_DIR", str(data_dir))
    out = tmp_path / "validated"
    arguments = ["validate", "sumo", str(MODEL), "ngsim_i80_chains", "--out", str(out)]
    arguments += ["--vehicles", "2", "--rollouts", "1", "--bootstrap", "50", "--seed", "1"]
    done = runner.invoke(app, arguments)
    assert done.exit_code == 0, done.output

    summary = json.loads((out / "summary.json").read_text())
    assert summary["passed"] and summary["sumo_matches_bayesdrive"] and summary["control_failed"]
    assert summary["vehicles"] == 2 and summary["seed"] == 1
    table = pd.read_csv(out / "distances.csv")
    matched = table[table["compared"] == "sumo vs bayesdrive"]
    assert sorted(matched["quantity"]) == ["acceleration", "gap", "speed"]
    assert (matched["w1_high"] <= matched["tolerance"]).all()
    control = table[table["compared"] == "sumo_control vs bayesdrive"]
    # The control misses by a margin, not by rounding: at least twice the tolerance somewhere.
    assert (control["w1"] > 2 * control["tolerance"]).any()
    # Both simulators against the data: finite distances with ordered intervals.
    against_data = table[table["compared"].str.endswith("vs data")]
    assert len(against_data) == 9
    assert np.isfinite(against_data["w1"]).all()
    assert (against_data["w1_low"] <= against_data["w1_high"]).all()
    windows = pd.read_csv(out / "windows.csv", dtype={"vehicle": str})
    assert windows["vehicle"].nunique() == 2
    assert (out / "distributions.png").stat().st_size > 0

    # The results folder is complete and kept: rerunning into it is refused.
    assert runner.invoke(app, arguments).exit_code == 2


def test_a_model_sumo_cannot_run_or_a_bad_window_is_refused_before_any_work(tmp_path):
    merging = MODELS / "ngsim_merge_episodes_cidm_smc.nc"  # the Cooperative IDM: no SUMO type
    out = tmp_path / "refused"
    done = runner.invoke(
        app, ["validate", "sumo", str(merging), "ngsim_i80_chains", "--out", str(out)]
    )
    assert done.exit_code == 2
    assert "the result is of 'cidm'" in " ".join(done.output.split())
    done = runner.invoke(
        app,
        ["validate", "sumo", str(MODEL), "ngsim_i80_chains", "--window", "late", "--out", str(out)],
    )
    assert done.exit_code == 2 and "--window 'late'" in done.output
    assert not out.exists()
