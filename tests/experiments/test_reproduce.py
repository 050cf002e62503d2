"""The main job at its quick size: every experiment runs on the real data into one HTML report,
and a re-run reuses finished steps."""

import html
import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bayesdrive.cli.main import app
from bayesdrive.data import registry

SECTIONS = (
    "Highway experiment",
    "Merging experiment",
    "Per-vehicle parameters",
    "The paper's filter against the exact posterior",
    "Turing test",
    "Scene generation",
    "Generalisation to held-out data sets",
    "Prior sensitivity",
    "Model criticism",
    "How this report was made",
    "Steps and their times",
)


@pytest.mark.extended
@pytest.mark.slow
@pytest.mark.realdata
def test_quick_reproduction_writes_the_report_and_full_adds_the_left_out_steps(
    data_dir, holdout_dir, tmp_path, monkeypatch
):
    monkeypatch.setenv("BAYESDRIVE_DATA_DIR", str(data_dir))
    monkeypatch.setenv("BAYESDRIVE_HOLDOUT_DIR", str(holdout_dir))
    out = tmp_path / "quick"
    runner = CliRunner()
    # Without --full, the Turing test and the held-out data sets are left out, and said to be.
    first = runner.invoke(app, ["reproduce", "--quick", "--out", str(out)])
    assert first.exit_code == 0, first.output
    page = (out / "report.html").read_text()
    for section in SECTIONS:
        assert html.escape(section) in page
    assert page.count(html.escape("`bayesdrive reproduce --full` runs it")) == 2
    assert not (out / "turing.json").exists() and not (out / "holdout_evaluation.json").exists()
    main_steps = [s["step"] for s in json.loads((out / "step_times.json").read_text())]
    assert "Turing test" not in main_steps and "model export" in main_steps
    evaluation = out / "highway" / "ngsim_i80_chains" / "evaluation.json"
    stamp = evaluation.stat().st_mtime_ns

    # --full over that folder runs only the steps it left out.
    full = runner.invoke(app, ["reproduce", "--quick", "--full", "--out", str(out)])
    assert full.exit_code == 0, full.output
    assert evaluation.stat().st_mtime_ns == stamp
    page = (out / "report.html").read_text()
    for section in SECTIONS:
        assert html.escape(section) in page
    assert "--full` runs it" not in html.unescape(page)
    assert page.count("data:image/png;base64,") >= 6
    # Every announced step has its time, and the total is their sum (to the rounding).
    steps = json.loads((out / "step_times.json").read_text())
    assert steps[-1]["step"] == "total" and "model export" in [s["step"] for s in steps]
    assert {"Turing test", "generalisation on held-out data sets"} <= {s["step"] for s in steps}
    assert all(s["seconds"] >= 0 for s in steps)
    assert abs(sum(s["seconds"] for s in steps[:-1]) - steps[-1]["seconds"]) < 0.1 * len(steps)
    # The quick run evaluates one held-out set and criticises one data set, and names the others.
    holdout = json.loads((out / "holdout_evaluation.json").read_text())
    assert list(holdout["data_sets"]) == ["ngsim_i80_pairs_a"]
    assert set(holdout["left_out_by_settings"]) == set(registry.HOLDOUT) - {"ngsim_i80_pairs_a"}
    assert not (out / "criticism" / "openacc_vicolungo_human").exists()
    for name in [*holdout["left_out_by_settings"], "openacc_vicolungo:human"]:
        assert name in page

    highway = json.loads((out / "highway" / "ngsim_i80_chains" / "evaluation.json").read_text())
    models = highway["models"]
    assert {"idm-smc", "idm-pf", "idm-default", "idm-nls", "idm-lm", "cv", "ca", "blackbox"} <= set(
        models
    )
    for result in models.values():
        assert result["rmse_position_m"]["mean"] >= 0
        assert len(result["rmse_position_m"]["by_step"]["mean"]) == 51
        events = result["undesirable_events"]["by_step"]["mean"]
        assert len(events) == 51 and events == sorted(events)  # a share so far never falls

    # The criticism's final model stands beside the IDM wherever the IDM is: the highway table,
    # the Turing test and models/ (when the criticism adopted a cause on this data set).
    criticism = json.loads((out / "criticism" / "ngsim_i80_chains" / "criticism.json").read_text())
    final = criticism["model"]
    # The final model is the base extended by the adopted causes; the last round adopted nothing.
    assert final.split("+")[0] == "idm"
    assert sorted(final.split("+")[1:]) == sorted(criticism["adopted"])
    last = criticism["rounds"][-1]
    assert not last["adopted"] or len(criticism["rounds"]) == criticism["settings"]["max_rounds"]
    if final != "idm":
        assert f"{final}-smc" in models
        turing = json.loads((out / "turing.json").read_text())
        assert f"{final}-smc" in turing["classifier"]["ngsim_i80_chains"]
        assert (out / "models" / f"ngsim_i80_chains_{final.replace('+', '_')}_smc.md").exists()

    merge = json.loads((out / "merge.json").read_text())
    assert {"cidm-smc", "idm-lm", "cidm-c1", "idm-nomerge", "cv"} <= set(merge["models"])
    cooperation = merge["cidm_posterior"]["c"]
    assert 0 <= cooperation["q05"] <= cooperation["mean"] <= cooperation["q95"] <= 1
    assert (out / "models" / "ngsim_merge_episodes_cidm_smc.md").exists()

    # The code that made them is recorded: in the report, the model cards and every result.
    assert "Code: bayesdrive" in page
    card = (out / "models" / "ngsim_merge_episodes_cidm_smc.md").read_text()
    assert "- fitted by: bayesdrive" in card and "not recorded" not in card
    # The answer sheet is kept out of the folder of clips meant to be judged blind.
    turing = json.loads((out / "turing.json").read_text())
    assert Path(turing["answer_sheet"]).parent != Path(turing["clips"])
    assert not list(Path(turing["clips"]).glob("*.json"))
    assert Path(turing["answer_sheet"]).name in html.unescape(page)

    # A re-run rebuilds the report from the saved steps without recomputing them.
    again = runner.invoke(app, ["report", str(out)])
    assert again.exit_code == 0, again.output
    assert evaluation.stat().st_mtime_ns == stamp
    assert "Turing test" in [s["step"] for s in json.loads((out / "step_times.json").read_text())]

    # A complete folder is kept: other settings are refused rather than mixed in, unless --force.
    mixed = runner.invoke(app, ["reproduce", "--full", "--out", str(out)])
    assert mixed.exit_code == 2 and "other settings (quick: True there, False here)" in " ".join(
        mixed.output.split()
    )
    assert evaluation.stat().st_mtime_ns == stamp


@pytest.mark.realdata
def test_the_criticism_reads_ngsim_scenes_after_the_pilots_and_every_other_set_from_its_first(
    data_dir, monkeypatch
):
    """The full run's criticism: NGSIM I-80's scenes 9-40 (the first 8 were the pilot), every
    scene of OpenACC's human recordings (fewer than 32); the quick run reads the first scene."""
    from bayesdrive.experiments.paper import FULL, QUICK, criticised_scenes, highway_data

    monkeypatch.setenv("BAYESDRIVE_DATA_DIR", str(data_dir))
    ngsim = registry.load("ngsim_i80_chains")
    order = list(dict.fromkeys(ngsim.scenes["scene_id"]))
    assert criticised_scenes("ngsim_i80_chains", ngsim, FULL) == order[8:40]
    assert criticised_scenes("ngsim_i80_chains", ngsim, QUICK) == order[:1]
    human = highway_data("openacc_vicolungo")["openacc_vicolungo:human"]
    assert criticised_scenes("openacc_vicolungo:human", human, FULL) == list(
        dict.fromkeys(human.scenes["scene_id"])
    )


def test_a_step_boundary_releases_the_compiled_programs_of_the_step_before(tmp_path):
    """Announcing a step drops the engines' cached chunk programs and JAX's own caches, so a
    jitted function traces again after it (a reproduction kept thousands of programs to its end
    and ran out of memory)."""
    import jax
    import jax.numpy as jnp

    from bayesdrive.experiments.paper import StepClock
    from bayesdrive.inference.core import vehicles

    traced = []

    @jax.jit
    def double(x):
        traced.append(1)
        return 2 * x

    double(jnp.ones(3))
    double(jnp.ones(3))
    vehicles._COMPILED["a kept program"] = object()
    assert len(traced) == 1
    clock = StepClock(tmp_path, progress=lambda step: None)
    clock("the next step")
    assert "a kept program" not in vehicles._COMPILED
    double(jnp.ones(3))
    assert len(traced) == 2
    assert [row["step"] for row in clock.steps] == ["the next step"]
