"""Simulation-based calibration at CI size: smc, nuts and emcee pass, the sd-doubled model fails.

One SBC study per engine (seed 11): R = 30 replications of 64 steps, three
parameters (tau, a_max, sigma), L = 99 ranks in 5 bins. Verdicts use the module's own rule:
chi-square per parameter at alpha / K = 0.01 / 3 (Bonferroni). The same runs give the coverage
check: on data simulated from prior draws, the central 90% intervals of an exact posterior hold
the truth with probability 0.9 per parameter (averaged over the prior), so the covered count is
Binomial(30, 0.9); it is tested two-sided at 0.001 / 3.

A calibrated engine could fail the chi-square check by chance in at most 1% of seeds; the seed is
fixed, so a failure here is reproducible and means a real departure. The power check fits the
sd-doubled likelihood with the same seed and must be rejected (smc here; every engine in
``benchmarks/bench_sbc.py``).
"""

import json

import jax
import numpy as np
import pytest
import scipy.stats
from typer.testing import CliRunner

from bayesdrive.cli.main import app
from bayesdrive.cli.sbc_cmd import write_outcome
from bayesdrive.drivers.base import CarFollowingInputs, EgoState
from bayesdrive.drivers.idm import IDM
from bayesdrive.inference.diagnostics.sbc import (
    choose_bins,
    posterior_ranks,
    run_sbc,
    sd_doubled,
    uniformity_tests,
)
from bayesdrive.inference.engines import emcee, nuts, smc

SEED = 11
NAMES = ("tau", "a_max", "sigma")
REPLICATIONS = 30
STEPS = 64
ALPHA = 0.01
COVERAGE_ALPHA = 0.001
# Small engine settings: enough draws for 99 ranks, short runs.
ENGINES = {
    "smc": (smc.run, {"num_particles": 400}),
    "nuts": (nuts.run, {"num_particles": 400, "num_warmup": 150}),
    "emcee": (emcee.run, {"num_particles": 400, "num_steps": 400}),
}


def study(name: str, fit_model=IDM):
    engine, options = ENGINES[name]
    return run_sbc(
        jax.random.key(SEED),
        engine,
        engine_name=name,
        model=IDM,
        params=NAMES,
        fit_model=fit_model,
        num_replications=REPLICATIONS,
        num_steps=STEPS,
        alpha=ALPHA,
        engine_options=options,
        seed=SEED,
    )


# The cross-check engines' studies are in the extended tier (reports/ci_time.md): CI keeps smc's,
# the sd-doubled negative control and their exact-posterior tests (test_nuts.py, test_emcee.py).
@pytest.mark.parametrize(
    "engine",
    [pytest.param(name, marks=[pytest.mark.extended] if name != "smc" else []) for name in ENGINES],
)
def test_engine_is_calibrated_covers_the_truth_and_writes_its_outcome(engine, tmp_path):
    # One test per engine: its study runs once, on one worker (a module fixture shared by several
    # tests was built again on each worker that took one of them).
    outcome = study(engine)
    shows_no_miscalibration(outcome)
    covers_truth_at_nominal_rate(outcome)
    writes_outcome_files_and_digest(outcome, tmp_path)


def shows_no_miscalibration(outcome):
    level = ALPHA / len(NAMES)
    assert outcome.bins == 5 and outcome.counts.sum(axis=1).tolist() == [REPLICATIONS] * 3
    assert outcome.calibrated, (
        f"{outcome.engine}: chi-square p-values {outcome.chi2_pvalue} (level {level}), "
        f"bins {outcome.counts.tolist()}"
    )


def covers_truth_at_nominal_rate(outcome):
    covered = np.rint(outcome.coverage * REPLICATIONS).astype(int)
    for name, count in zip(NAMES, covered, strict=True):
        p = scipy.stats.binomtest(int(count), REPLICATIONS, outcome.interval).pvalue
        assert p >= COVERAGE_ALPHA / len(NAMES), (
            f"{outcome.engine}: {name} covered {count}/{REPLICATIONS} (nominal 0.9), p={p:.2g}"
        )


def writes_outcome_files_and_digest(outcome, tmp_path):
    files = write_outcome(outcome, tmp_path, "study")
    assert [f.name for f in files] == ["study_ranks.png", "study_ranks.csv", "study.json"]
    digest = json.loads((tmp_path / "study.json").read_text())
    assert digest["calibrated"] == outcome.calibrated and digest["seed"] == SEED
    assert digest["bonferroni_level"] == pytest.approx(ALPHA / len(NAMES))
    rows = (tmp_path / "study_ranks.csv").read_text().splitlines()
    assert len(rows) == REPLICATIONS + 1
    assert rows[0] == "replication,truth_tau,truth_a_max,truth_sigma,rank_tau,rank_a_max,rank_sigma"


def test_sd_doubled_engine_is_rejected_with_same_seed():
    # One engine at CI size (compilations dominate); benchmarks/bench_sbc.py checks all three.
    wrong = study("smc", fit_model=sd_doubled(IDM))
    assert wrong.fit_model == "idm-sd-doubled"
    assert not wrong.calibrated
    # Twice the noise sd in the likelihood halves sigma's posterior: truths rank at the top.
    sigma = NAMES.index("sigma")
    assert wrong.chi2_pvalue[sigma] < ALPHA / len(NAMES)
    assert np.mean(wrong.ranks[:, sigma] == 99) > 0.5


def test_sd_doubled_wrapper_scores_twice_the_sd():
    params = IDM.defaults()
    state, inputs = EgoState(0.0, 10.0), CarFollowingInputs(20.0, 10.0, 1.0, 0.1)
    observed = EgoState(1.0, 10.0)
    doubled = params._replace(sigma=2 * params.sigma)
    assert sd_doubled(IDM).transition_logpdf(params, state, observed, inputs) == pytest.approx(
        IDM.transition_logpdf(doubled, state, observed, inputs)
    )


def test_ranks_count_draws_below_the_truth():
    # Replication 0 has draws 0..9, replication 1 draws 10..19 (chain 0 then chain 1).
    draws = np.stack([np.arange(10.0).reshape(2, 5), 10 + np.arange(10.0).reshape(2, 5)], -1)
    truth = np.array([[3.5], [25.0]])
    ranks = posterior_ranks({"tau": draws}, ("tau",), truth, num_ranks=10)
    assert ranks[:, 0].tolist() == [4, 10]
    # Five of ten draws, evenly spaced: 0, 2, 4, 6, 8 -> two of them below 3.5.
    assert posterior_ranks({"tau": draws}, ("tau",), truth, num_ranks=5)[0, 0] == 2


def test_bins_divide_ranks_and_keep_five_expected():
    assert choose_bins(99, 40) == 5
    assert choose_bins(99, 200) == 20
    assert choose_bins(99, 100) == 20
    with pytest.raises(ValueError, match="no chi-square binning"):
        choose_bins(99, 9)


def test_uniformity_tests_accept_uniform_and_reject_lumped_ranks():
    rng = np.random.default_rng(5)
    uniform = rng.integers(0, 100, size=(400, 1))
    lumped = np.clip(rng.normal(50, 10, size=(400, 1)).round(), 0, 99).astype(int)
    key = jax.random.key(0)
    _, _, p_uniform, ks_uniform = uniformity_tests(key, uniform, 99, 10)
    counts, _, p_lumped, ks_lumped = uniformity_tests(key, lumped, 99, 10)
    assert counts.sum() == 400
    # Seeded draws: uniform ranks pass at 1%, ranks piled in the middle fail both tests hard.
    assert p_uniform[0] > 0.01 and ks_uniform[0] > 0.01
    assert p_lumped[0] < 1e-10 and ks_lumped[0] < 1e-10


def test_too_few_draws_for_the_ranks_is_an_error():
    draws = np.zeros((1, 50, 2))
    with pytest.raises(ValueError, match="fewer than the 99 ranks"):
        posterior_ranks({"tau": draws}, ("tau",), np.zeros((2, 1)), 99)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--engine", "nope"], "unknown engine"),
        (["--engine", "hierarchical"], "own population prior"),
        (["--engine", "smc", "--params", "tau,wings"], "no parameter"),
        (["--engine", "smc", "--model", "idm+wings"], "wings"),
        (["--engine", "smc", "--model", "cidm"], "merge scene"),
    ],
)
def test_sbc_command_refuses_bad_requests(args, message):
    run = CliRunner().invoke(app, ["sbc", *args, "--replications", "20"])
    assert run.exit_code == 2
    assert message in run.output


def test_sbc_command_calibrates_any_registered_model():
    """`--model` reaches the study: the OVM's own parameters are simulated, fitted and ranked
    (by lm, the cheapest engine to compile: the wiring, not the engine, is under test)."""
    run = CliRunner().invoke(
        app,
        [
            *("sbc", "--engine", "lm", "--model", "ovm", "--replications", "10"),
            *("--steps", "16", "--particles", "128", "--seed", "1", "--json", "-"),
        ],
    )
    assert run.exit_code == 0, run.output
    digest = json.loads(run.output)
    assert digest["model"] == digest["fit_model"] == "ovm"
    assert list(digest["parameters"]) == ["kappa", "v_max", "s_c", "sigma"]
