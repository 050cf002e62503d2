"""`bayesdrive fit` through typer's CliRunner."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from bayesdrive.cli.main import app
from bayesdrive.data.registry import HOLDOUT
from bayesdrive.inference.output import load_result, metadata

runner = CliRunner()
# One chain file (fast to read) with samples of negative bumper gap, which the reader flags.
CHAIN = "ngsim_i80_chains/124_136_140_146_162_164.csv"


def one_line(text: str) -> str:
    """Rich wraps long lines at the console width; compare messages with whitespace collapsed."""
    return " ".join(text.split())


@pytest.mark.realdata
def test_fit_writes_result_summary_and_plots(data_dir, tmp_path):
    out = tmp_path / "fit"
    args = ["fit", str(data_dir / CHAIN), "--vehicles", "2", "--particles", "100"]
    args += ["--params", "v_des,sigma", "--seed", "3", "--out", str(out), "--json", "-"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    printed = json.loads(result.stdout)  # nothing but the JSON on stdout
    assert printed == json.loads((out / "summary.json").read_text())
    assert sorted(p.name for p in out.iterdir()) == [
        "convergence.png",
        "ess.png",
        "manifest.json",
        "result.nc",
        "summary.json",
        "unique_particles.png",
    ]
    tree = load_result(out / "result.nc")
    meta = metadata(tree)
    assert (meta["engine"], meta["seed"], meta["window"]) == ("smc", 3, "fit")
    assert meta["data_source"] == str(data_dir / CHAIN)
    # The chains hold samples with negative bumper gaps: counted, and never fitted.
    assert meta["flagged_samples"] > 0 and printed["flagged_samples"] == meta["flagged_samples"]
    assert tree["posterior"]["sigma"].shape == (1, 100, 2)
    assert list(printed["vehicles"]) == [str(v) for v in tree["posterior"]["vehicle"].values]


@pytest.mark.realdata
def test_fit_runs_the_paper_filter_with_epochs(data_dir, tmp_path):
    args = ["fit", str(data_dir / CHAIN), "--engine", "pf", "--epochs", "2"]
    args += ["--vehicles", "2", "--particles", "64", "--params", "v_des,sigma"]
    result = runner.invoke(app, [*args, "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    meta = metadata(load_result(tmp_path / "result.nc"))
    assert meta["engine"] == "pf" and meta["engine_options"]["epochs"] == 2
    assert "pf on idm" in one_line(result.stdout)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--window", "heldout"], "held-out steps are never fitted"),
        (["--epochs", "3"], "--epochs applies to --engine pf only"),
        (["--engine", "gibbs"], "unknown engine 'gibbs'"),
        (["--params", "v_des,speed"], "has no parameter(s) ['speed']"),
        (["--model", "krauss"], "unknown driver model 'krauss'"),
    ],
)
def test_bad_options_end_with_a_clear_error(data_dir, tmp_path, extra, message):
    result = runner.invoke(app, ["fit", str(data_dir / CHAIN), *extra, "--out", str(tmp_path)])
    assert result.exit_code == 2
    assert message in one_line(result.stderr)
    assert not any(tmp_path.iterdir())  # nothing written


def test_held_out_data_is_never_fitted(tmp_path):
    name = next(iter(HOLDOUT))
    result = runner.invoke(app, ["fit", name, "--out", str(tmp_path)])
    assert result.exit_code == 2
    assert "held out for evaluation only" in one_line(result.stderr)
    assert not any(tmp_path.iterdir())


@pytest.mark.realdata
@pytest.mark.parametrize("engine", ["nuts", "emcee", "lm"])
def test_fit_runs_the_cross_check_engines(data_dir, tmp_path, engine):
    """Every engine behind --engine writes its result and summary; the per-step filter pictures
    exist only for the filters, so the others must not fail on them."""
    args = ["fit", str(data_dir / CHAIN), "--engine", engine, "--vehicles", "1"]
    args += ["--particles", "200", "--params", "v_des,sigma", "--seed", "2", "--out", str(tmp_path)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "manifest.json",
        "result.nc",
        "summary.json",
    ]
    tree = load_result(tmp_path / "result.nc")
    assert metadata(tree)["engine"] == engine
    assert "wrote result.nc, summary.json to" in one_line(result.stdout)
