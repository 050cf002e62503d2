"""Convergence checks after every fit, on posteriors whose convergence is known by construction.

Draws are made here with numpy (seeded), not by an engine: independent normal chains must pass
every check (negative control), and each defect (a shifted chain, a sticky chain, a short emcee
run, scattered SMC replicates) must be named with its vehicle and parameter.
"""

from __future__ import annotations

import numpy as np
import pytest

from bayesdrive.data.views import FollowerArrays
from bayesdrive.inference.core.output import REQUIRED_METADATA, build_tree
from bayesdrive.inference.diagnostics.convergence import (
    ESS_MIN,
    RHAT_MAX,
    chain_problems,
    check_convergence,
    next_step,
)

VEHICLES = ("a", "b")
CHAINS, DRAWS = 4, 1000


def arrays() -> FollowerArrays:
    steps = np.zeros((len(VEHICLES), 3))
    return FollowerArrays(VEHICLES, *(steps,) * 6, mask=np.ones_like(steps), t=steps, dt=0.1)


def tree(posterior, engine, sample_stats=None, engine_options=None):
    chains, draws, _ = next(iter(posterior.values())).shape
    meta = {k: 0 for k in REQUIRED_METADATA} | {
        "engine": engine,
        "params": list(posterior),
        "engine_options": engine_options or {},
    }
    return build_tree(
        posterior=posterior,
        sample_stats=sample_stats or {},
        log_likelihood=np.zeros((chains, draws, len(VEHICLES), 3)),
        arrays=arrays(),
        metadata=meta,
    )


def independent(seed: int, chains: int = CHAINS, draws: int = DRAWS) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {name: rng.normal(size=(chains, draws, len(VEHICLES))) for name in ("v_des", "sigma")}


def named(report) -> set[tuple[str, str, str]]:
    return {(p.vehicle, p.param, p.check) for p in report.problems}


def test_independent_chains_pass_every_check():
    report = check_convergence(tree(independent(1), "nuts"))
    assert report.checks == ["spread", "rhat", "ess_bulk", "ess_tail"]
    assert report.unchecked is None
    assert report.problems == []


def test_a_collapsed_posterior_is_named_for_every_engine():
    """All draws of one vehicle's parameter equal (a particle set descended from one particle):
    named as collapsed, for smc with one replicate too, where nothing else is checked."""
    posterior = independent(6, chains=1)
    posterior["v_des"][:, :, 0] = 12.5
    for engine in ("smc", "pf", "nuts"):
        report = check_convergence(tree(posterior, engine))
        assert ("a", "v_des", "spread") in named(report)
        assert not any(p.vehicle == "b" and p.check == "spread" for p in report.problems)
    smc = check_convergence(tree(posterior, "smc"))
    assert smc.unchecked and "collapsed" in smc.problems[0].message()


def test_a_shifted_chain_fails_rhat_for_that_vehicle_and_parameter():
    posterior = independent(2)
    posterior["sigma"][0, :, 1] += 0.5  # chain 0 of vehicle b sits half an sd off
    report = check_convergence(tree(posterior, "nuts"))
    # The bulk ESS drops with it; nothing else is named.
    assert ("b", "sigma", "rhat") in named(report)
    assert {(p.vehicle, p.param) for p in report.problems} == {("b", "sigma")}
    problem = next(p for p in report.problems if p.check == "rhat")
    assert problem.value > RHAT_MAX
    assert "vehicle b, parameter sigma: R-hat" in problem.message()


def test_a_sticky_chain_fails_bulk_and_tail_ess():
    posterior = independent(3)
    rng = np.random.default_rng(4)
    sticky = np.zeros((CHAINS, DRAWS))
    for i in range(1, DRAWS):  # AR(1), rho 0.995: ESS about 4000 * 0.0025 = 10
        sticky[:, i] = 0.995 * sticky[:, i - 1] + np.sqrt(1 - 0.995**2) * rng.normal(size=CHAINS)
    posterior["v_des"][:, :, 0] = sticky
    report = check_convergence(tree(posterior, "nuts"))
    failed = named(report)
    assert {("a", "v_des", "ess_bulk"), ("a", "v_des", "ess_tail")} <= failed
    assert all(vehicle == "a" and param == "v_des" for vehicle, param, _ in failed)
    assert all(p.value < ESS_MIN for p in report.problems if p.check.startswith("ess"))
    # The per-vehicle checks an engine runs before extending itself name the same problems.
    names = tuple(posterior)
    for i, vehicle in enumerate(VEHICLES):
        draws = np.stack([posterior[name][:, :, i] for name in names], axis=-1)
        assert set(chain_problems(vehicle, names, draws)) == {
            p for p in report.problems if p.vehicle == vehicle
        }


def test_the_next_step_names_the_options_to_raise():
    nuts_options = {"num_samples": 250, "num_chains": 4, "num_warmup": 500, "max_extension": 8}
    assert "--draws 16000 --warmup 8000" in next_step("nuts", nuts_options)
    unextended = nuts_options | {"num_samples": 50, "max_extension": 1}  # 200 draws: no extension
    assert "--draws 1600 --warmup 1000" in next_step("nuts", unextended)
    assert "--steps 32000" in next_step("emcee", {"num_steps": 4000, "max_steps": 16000})
    assert "--particles" in next_step("smc", {})
    assert next_step("lm", {}) is None


@pytest.mark.parametrize(("tau", "fails"), [(10.0, False), (30.0, True)])
def test_an_emcee_run_shorter_than_50_autocorrelation_times_is_flagged(tau, fails):
    taus = np.array([[5.0, 5.0], [5.0, tau]])  # vehicle b, sigma
    stats = {
        "autocorr_time": (("vehicle", "param"), taus),
        "thin": (("vehicle",), np.ceil(taus.max(axis=1))),
        "autocorr_reliable": (("vehicle",), 50 * taus.max(axis=1) < 1000),
    }
    posterior = independent(5, chains=1, draws=4000)
    options = {"num_steps": 1500, "num_burn": 500}  # 1000 sampled steps
    report = check_convergence(tree(posterior, "emcee", stats, options))
    assert "autocorr" in report.checks and "rhat" not in report.checks  # one ensemble
    autocorr = [p for p in report.problems if p.check == "autocorr"]
    assert [(p.vehicle, p.param, p.value) for p in autocorr] == (
        [("b", "sigma", pytest.approx(1000 / tau))] if fails else []
    )


@pytest.mark.parametrize("stuck", [(0, 0), (0, 2)])
def test_an_emcee_vehicle_with_stuck_walkers_is_named(stuck):
    """The engine's count of walkers stuck in the kept steps: vehicle b with 2 is a problem
    whose message says so; with none (the negative control), no vehicle is named."""
    stats = {"stuck_walkers": (("vehicle",), np.array(stuck))}
    report = check_convergence(tree(independent(6, chains=1, draws=4000), "emcee", stats))
    assert "stuck_walkers" in report.checks
    found = [p for p in report.problems if p.check == "stuck_walkers"]
    assert [(p.vehicle, p.value) for p in found] == ([("b", 2.0)] if stuck[1] else [])
    assert all("2 walker(s) stuck" in p.message() for p in found)


def test_smc_replicates_that_disagree_are_flagged_and_one_replicate_is_unchecked():
    single = check_convergence(tree(independent(6, chains=1), "smc"))
    assert single.checks == ["spread"] and single.problems == []
    assert "replicates" in single.unchecked

    options = {"replicates": CHAINS}
    agreeing = check_convergence(tree(independent(7), "smc", engine_options=options))
    assert agreeing.problems == [] and "replicate_spread" in agreeing.checks
    posterior = independent(8)
    posterior["v_des"][:, :, 0] += np.array([0.0, 0.2, -0.2, 0.1])[:, None]  # replicate means
    scattered = check_convergence(tree(posterior, "smc", engine_options=options))
    assert ("a", "v_des", "replicate_spread") in named(scattered)
    assert {p.vehicle for p in scattered.problems} == {"a"}


@pytest.mark.parametrize(
    "moves, correlation", [((250, 40), (0.51, 0.05)), ((250, 40), (0.05, 0.05))]
)
def test_one_replicate_smc_names_vehicles_whose_closing_moves_ended_undecorrelated(
    moves, correlation
):
    """Vehicle a's closing moves ran to the cap (250) with its draws still correlated 0.51 with
    their start (criterion 0.1): the unchecked note names it, and nothing else. Negative control:
    at the cap but decorrelated (0.05), no vehicle is named."""
    stats = {
        "final_moves": (("chain", "vehicle"), np.array([moves])),
        "final_correlation": (("chain", "vehicle"), np.array([correlation])),
    }
    options = {"max_final_moves": 250, "decorrelation": 0.1, "num_particles": 1000}
    report = check_convergence(tree(independent(9, chains=1), "smc", stats, options))
    assert report.problems == []
    named_in_note = "closing moves of 1 vehicle(s)" in report.unchecked
    assert named_in_note == (correlation[0] > 0.1)
    if named_in_note:
        assert report.unchecked.endswith(
            ": a (rerun them with more --particles, or with replicates > 1 to measure their spread)"
        )
