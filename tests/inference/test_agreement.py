"""Convergence and agreement tables on constructed draws, and ``bayesdrive diagnose``.

Result B is built from result A's own draws (shifted or scaled), so every agreement figure has an
exact value: shifting by c moves the mean by c, keeps the sd and gives a Wasserstein distance of
exactly c; scaling by 1.2 around 0 gives an sd ratio of 1.2 and a distance of 0.2 mean|a|.
"""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from bayesdrive.cli.main import app
from bayesdrive.data.views import FollowerArrays
from bayesdrive.inference.core.output import build_tree, metadata, save_result
from bayesdrive.inference.diagnostics.agreement import (
    agreement_summary,
    agreement_table,
    convergence_table,
    mcse_mean,
    same_data,
)

VEHICLES = ("shifted-a-little", "shifted-a-lot", "scaled")


def arrays(vehicles=VEHICLES) -> FollowerArrays:
    ones = np.ones((len(vehicles), 2))
    return FollowerArrays(
        vehicle_ids=tuple(vehicles),
        v=ones,
        next_v=ones,
        dx=ones,
        gap=ones,
        lead_v=ones,
        has_leader=ones,
        mask=ones,
        t=ones,
        dt=0.1,
    )


def result(posterior, engine, *, sample_stats=None, source="constructed", vehicles=VEHICLES):
    chains, draws, _ = next(iter(posterior.values())).shape
    return build_tree(
        posterior=posterior,
        sample_stats=sample_stats or {},
        log_likelihood=np.zeros((chains, draws, len(vehicles), 2)),
        arrays=arrays(vehicles),
        metadata={
            "engine": engine,
            "model": "idm",
            "params": list(posterior),
            "fixed": {},
            "seed": 0,
            "data_source": source,
            "window": "fit",
            "num_particles": draws,
            "flagged_samples": 0,
        },
    )


@pytest.fixture(scope="module")
def pair():
    rng = np.random.default_rng(2)
    base = rng.normal(size=(4, 1000))  # 4 chains x 1000 independent draws
    base -= base.mean()  # exactly mean 0, so scaling leaves the mean at 0
    a = np.stack([base, base, base], axis=-1)
    flat = base.reshape(1, 4000)
    b = np.stack([flat + 0.05, flat + 0.5, 1.2 * flat], axis=-1)
    return result({"tau": a}, "nuts"), result({"tau": b}, "smc"), base


def test_agreement_numbers_are_exact_on_constructed_draws(pair):
    a, b, base = pair
    table = agreement_table({"nuts": a, "smc": b}).set_index("vehicle")
    little, lot, scaled = (table.loc[v] for v in VEHICLES)
    assert little["mean_diff_sd"] == pytest.approx(0.05 / base.std())
    assert lot["mean_diff_sd"] == pytest.approx(0.5 / base.std())
    assert little["sd_ratio"] == pytest.approx(1.0) and lot["sd_ratio"] == pytest.approx(1.0)
    assert scaled["sd_ratio"] == pytest.approx(1.2)
    assert little["wasserstein"] == pytest.approx(0.05)
    assert lot["wasserstein"] == pytest.approx(0.5)
    assert scaled["wasserstein"] == pytest.approx(0.2 * np.abs(base).mean())
    # 4000 independent draws: MCSE ~ 1/sqrt(4000), so 3 combined MCSE ~ 0.07 < 0.5.
    assert little["mc_tolerance"] < 0.1
    assert (little["agree_mean"], little["agree_sd"], little["agree"]) == (True, True, True)
    assert (lot["agree_mean"], lot["agree"]) == (False, False)
    assert (scaled["agree_mean"], scaled["agree_sd"], scaled["agree"]) == (True, False, False)
    summary = agreement_summary(table.reset_index()).iloc[0]
    assert summary["agree"] == pytest.approx(1 / 3)
    assert summary["max_abs_mean_diff_sd"] == pytest.approx(0.5 / base.std())


def test_convergence_flags_chains_that_disagree():
    rng = np.random.default_rng(4)
    mixed = rng.normal(size=(4, 500, 2))
    mixed[:2, :, 1] += 3.0  # vehicle 1: two chains sit 3 sds away from the other two
    diverging = np.zeros((4, 500, 2), dtype=bool)
    diverging[0, :7, 1] = True
    tree = result(
        {"tau": mixed},
        "nuts",
        sample_stats={"diverging": (("chain", "draw", "vehicle"), diverging)},
        vehicles=("good", "stuck"),
    )
    table = convergence_table(tree).set_index("vehicle")
    assert table.loc["good", "rhat"] < 1.01
    assert table.loc["stuck", "rhat"] > 1.5
    assert table.loc["stuck", "ess_bulk"] < 0.1 * table.loc["good", "ess_bulk"]
    assert table.loc["stuck", "divergences"] == 7 and table.loc["good", "divergences"] == 0


def test_single_chain_has_no_rhat_and_reports_autocorrelation():
    draws = np.random.default_rng(6).normal(size=(1, 300, 1))
    stats = {
        "autocorr_time": (("vehicle", "param"), np.array([[12.5]])),
        "thin": (("vehicle",), np.array([13])),
        "autocorr_reliable": (("vehicle",), np.array([True])),
    }
    tree = result({"tau": draws}, "emcee", sample_stats=stats, vehicles=("v",))
    row = convergence_table(tree).iloc[0]
    assert np.isnan(row["rhat"])
    assert (row["autocorr_time"], row["thin"], row["autocorr_reliable"]) == (12.5, 13, 1)


def test_results_on_other_data_are_refused(pair):
    a, _, _ = pair
    other = result({"tau": np.zeros((1, 10, 3))}, "smc", source="elsewhere")
    with pytest.raises(ValueError, match="not on the same data"):
        same_data({"nuts": a, "smc": other})
    disjoint = result({"tau": np.zeros((1, 10, 1))}, "smc", vehicles=("nobody",))
    with pytest.raises(ValueError, match="share no vehicle"):
        agreement_table({"nuts": a, "smc": disjoint})


def test_diagnose_command_json_and_pictures(pair, tmp_path):
    a, b, base = pair
    paths = [save_result(a, tmp_path / "nuts.nc"), save_result(b, tmp_path / "smc.nc")]
    out = tmp_path / "diag"
    run = CliRunner().invoke(app, ["diagnose", *map(str, paths), "--json", "-", "--out", str(out)])
    assert run.exit_code == 0, run.output
    report = json.loads(run.stdout)
    assert set(report["results"]) == {"nuts", "smc"}
    assert report["results"]["smc"]["worst"]["tau"]["max_rhat"] is None  # one chain
    assert report["results"]["nuts"]["worst"]["tau"]["max_rhat"] < 1.01
    rows = {r["vehicle"]: r for r in report["agreement"]["per_vehicle"]}
    assert rows["shifted-a-lot"]["mean_diff_sd"] == pytest.approx(0.5 / base.std())
    assert rows["shifted-a-lot"]["agree"] is False
    assert {p.name for p in out.iterdir()} >= {
        "marginals_tau.png",
        "agreement_heatmap.png",
        "agreement.csv",
        "convergence_nuts.csv",
        "convergence_smc.csv",
    }


def test_diagnose_refuses_missing_files(tmp_path):
    run = CliRunner().invoke(app, ["diagnose", str(tmp_path / "absent.nc")])
    assert run.exit_code == 2
    assert "no such result file" in run.output


def test_replicate_runs_take_their_standard_error_from_the_replicate_means():
    # Four replicates: the same iid draws shifted by an offset per replicate. Their MCSE is the
    # offsets' sd / 2 exactly; the autocorrelation estimate sees four nearly iid chains and would
    # report about sd / sqrt(4000), far smaller.
    draws = np.random.default_rng(3).normal(size=1000)
    offsets = np.array([0.0, 0.1, -0.1, 0.3])
    tau = np.stack([np.stack([draws + c] * 3, axis=-1) for c in offsets])
    plain = result({"tau": tau}, "smc")
    replicated = build_tree(
        posterior={"tau": tau},
        sample_stats={},
        log_likelihood=np.zeros((4, 1000, 3, 2)),
        arrays=arrays(),
        metadata={**metadata(plain), "engine_options": {"replicates": 4}},
    )
    expected = offsets.std(ddof=1) / 2.0
    assert np.allclose(mcse_mean(replicated)["tau"].values, expected)
    assert np.all(mcse_mean(plain)["tau"].values < 0.5 * expected)
    table = convergence_table(replicated)
    assert np.allclose(table["ess_mean"], (table["sd"] / expected) ** 2)


def test_the_sd_criterion_allows_for_monte_carlo_error_and_still_catches_a_wrong_spread():
    # Two exact samplers of one skewed marginal (lognormal, sigma 0.5): 1000 independent draws
    # each, for 300 vehicles (seed 20261127). Their sds differ by over 10% in about one pair in
    # seven, so a fixed 10% rule calls correct engines wrong; allowing 3 combined Monte Carlo
    # standard errors of the sds, at most 2% of the pairs may disagree. The negative control: a
    # sampler whose spread is 30% too wide must be caught in at least 80% of the pairs.
    rng = np.random.default_rng(20261127)
    vehicles = [f"v{i}" for i in range(300)]

    def sampler(scale=1.0):
        draws = scale * rng.lognormal(0.0, 0.5, size=(1, 1000, len(vehicles)))
        return result({"tau": draws}, "exact", vehicles=vehicles)

    exact_a, exact_b, too_wide = sampler(), sampler(), sampler(scale=1.3)
    both_exact = agreement_table({"a": exact_a, "b": exact_b})
    fixed_rule_misses = np.mean(
        np.maximum(both_exact["sd_ratio"], 1 / both_exact["sd_ratio"]) > 1.1
    )
    assert fixed_rule_misses > 0.05
    assert np.mean(~both_exact["agree_sd"]) <= 0.02
    assert (both_exact["sd_mc_tolerance"] > 0.1 * both_exact[["sd_a", "sd_b"]].min(axis=1)).any()
    wrong = agreement_table({"a": exact_a, "wide": too_wide})
    assert np.mean(~wrong["agree_sd"]) >= 0.8
