"""The Gipps (1981) model pinned against hand arithmetic and the paper's own formula, its density
against scipy, its parameters recovered from an independent simulator, and ``fit --model gipps``
run through every engine of the CLI (pmmh refused)."""

from __future__ import annotations

import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats
from typer.testing import CliRunner

from bayesdrive.cli.main import app
from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import CarFollowingInputs, EgoState
from bayesdrive.drivers.gipps import GIPPS, gipps_acceleration
from bayesdrive.inference import fit
from bayesdrive.inference.core.output import load_result, metadata
from bayesdrive.inference.engines import nuts, smc
from bayesdrive.inference.population import hierarchical
from bayesdrive.simulation.generate import equilibrium_gap

DT = 0.1
# Gipps' own simulation values: a 1.7, b 3.4, b-hat 3.2 m/s^2, V 20 m/s; margin 2 m.
HAND = GIPPS.params_type(v_des=20.0, a_max=1.7, b_max=3.4, b_lead=3.2, d_min=2.0, sigma=0.3)
ACC_TOL = 1e-4  # float32 speeds of ~10 m/s carry ~1e-6 m/s, divided by dt = 0.1


def acceleration(v, gap, lead_v, has_leader=1.0, params=HAND):
    inputs = CarFollowingInputs(gap=gap, lead_v=lead_v, has_leader=has_leader, dt=DT)
    state = EgoState(x=jnp.zeros(()), v=jnp.asarray(v))
    return float(gipps_acceleration(params, state, inputs))


def test_free_speed_wins_with_a_long_gap():
    # v=10, V=20: v_free = 10 + 2.5 * 1.7 * 0.1 * (1 - 0.5) * sqrt(0.025 + 0.5)
    #           = 10 + 0.2125 * 0.7245688 = 10.1539709, so a = 1.539709.
    # The safe speed, gap 12, lead_v 8: 2 (12 - 2) - 10 * 0.1 + 64 / 3.2 = 39,
    #   -0.34 + sqrt(0.34^2 + 3.4 * 39) = -0.34 + 11.5202257 = 11.180226 > v_free.
    assert acceleration(10.0, 12.0, 8.0) == pytest.approx(1.539709, abs=ACC_TOL)


def test_safe_speed_wins_with_a_short_gap():
    # Same, gap 6: 2 (6 - 2) - 1 + 20 = 27, -0.34 + sqrt(0.1156 + 91.8) = -0.34 + 9.5872624
    #   = 9.2472624 < v_free, so a = (9.2472624 - 10) / 0.1 = -7.527376.
    assert acceleration(10.0, 6.0, 8.0) == pytest.approx(-7.527376, abs=ACC_TOL)


def test_free_road_uses_the_free_speed_whatever_the_gap():
    # v=25 above V=20: 25 + 0.425 * (1 - 1.25) * sqrt(1.275) = 25 - 0.10625 * 1.1291590
    #   = 24.8800269, so a = -1.199731 (the free law slows a car above its desired speed).
    for junk_gap in (0.0, 1.0, float("nan")):
        assert acceleration(25.0, junk_gap, 0.0, has_leader=0.0) == pytest.approx(
            -1.199731, abs=ACC_TOL
        )


@pytest.mark.parametrize("gap", [2.5, 2.0, 0.5])
def test_a_stop_within_the_margin_of_a_stopped_leader_is_one_step_away(gap):
    # lead_v = 0, v = 10: at gap 2.5 the bracket is 2 * 0.5 - 1 = 0, so v_safe = -0.34 + 0.34 = 0;
    # closer, the radicand is negative (no safe speed exists) and the target is a stop too.
    assert acceleration(10.0, gap, 0.0) == pytest.approx(-100.0, abs=ACC_TOL)


def paper_free_speed(v, V, a, tau, gain=2.5):
    """Gipps (1981) eq. (2): the speed one reaction time on, unhindered (``gain`` is his 2.5)."""
    return v + gain * a * tau * (1 - v / V) * np.sqrt(0.025 + v / V)


def paper_safe_speed(v, lead_v, gap, b, b_hat, margin, tau):
    """Gipps (1981) eq. (3) in his notation: b and b_hat negative; x_{n-1} - s_{n-1} - x_n is the
    bumper gap minus the margin (s_{n-1} = leader length + margin). NaN where no safe speed
    exists."""
    spacing = gap - margin
    radicand = b**2 * tau**2 - b * (2 * spacing - v * tau - lead_v**2 / b_hat)
    return b * tau + np.sqrt(np.where(radicand >= 0, radicand, np.nan))


def test_matches_the_papers_formula_on_random_situations():
    rng = np.random.default_rng(7)
    n = 2000
    v, lead_v = rng.uniform(0, 30, n), rng.uniform(0, 30, n)
    gap = rng.uniform(3, 80, n)
    V, a = rng.uniform(5, 45, n), rng.uniform(0.2, 5, n)
    b, b_hat, margin = rng.uniform(0.5, 10, n), rng.uniform(0.5, 10, n), rng.uniform(0.5, 3, n)
    free = paper_free_speed(v, V, a, DT)
    safe = paper_safe_speed(v, lead_v, gap, -b, -b_hat, margin, DT)
    keep = np.isfinite(safe)  # the model's floor there is checked by hand above
    expected = (np.maximum(np.minimum(free, safe), 0.0) - v) / DT
    params = GIPPS.params_type(V, a, b, b_hat, margin, np.full(n, 0.3))
    inputs = CarFollowingInputs(gap=gap, lead_v=lead_v, has_leader=np.ones(n), dt=DT)
    got = np.asarray(
        jax.jit(gipps_acceleration)(params, EgoState(np.zeros(n), v), inputs), np.float64
    )
    # Both branches occur often, so both are checked.
    assert keep.mean() > 0.9 and 0.1 < (safe < free)[keep].mean() < 0.9
    # float32 speeds of up to 30 m/s, divided by dt = 0.1.
    np.testing.assert_allclose(got[keep], expected[keep], rtol=1e-4, atol=1e-3)


def test_gradients_are_finite_on_free_road_and_past_the_safe_limit():
    def mean_acc(theta, v, gap, has_leader):
        params = GIPPS.params_type(*theta)
        inputs = CarFollowingInputs(gap=gap, lead_v=jnp.asarray(5.0), has_leader=has_leader, dt=DT)
        return gipps_acceleration(params, EgoState(jnp.zeros(()), v), inputs)

    theta = tuple(jnp.asarray(float(x)) for x in HAND)
    grad = jax.grad(mean_acc)
    for v, gap, has_leader in [(10.0, jnp.nan, 0.0), (10.0, 0.5, 1.0), (0.0, 30.0, 1.0)]:
        values = grad(theta, jnp.asarray(v), jnp.asarray(gap), jnp.asarray(has_leader))
        assert all(np.isfinite(float(g)) for g in values), (v, gap, values)


def test_one_step_density_is_the_gaussian_position_increment():
    # a ~ N(a_G, sigma^2): the increment is N(v dt + a_G dt^2 / 2, (sigma dt^2 / 2)^2).
    # Implied accelerations -7.8 to -7.2 m/s^2: inside the physical limits.
    state, inputs = EgoState(0.0, 10.0), CarFollowingInputs(6.0, 8.0, 1.0, DT)
    for dx in (0.961, 0.962, 0.964):
        logp = float(GIPPS.transition_logpdf(HAND, state, EgoState(dx, 9.3), inputs))
        expected = stats.norm.logpdf(dx, 10.0 * DT - 7.527376 * DT**2 / 2, 0.3 * DT**2 / 2)
        assert logp == pytest.approx(expected, abs=1e-3)


def hardest_braking(leader_deceleration: float) -> float:
    """Hardest deceleration of a noiseless Gipps follower behind a leader that cruises at 15 m/s
    and then brakes at ``leader_deceleration`` to a stop (states advanced here)."""
    params = HAND._replace(sigma=0.0)
    lead_v, v, gap, hardest = 15.0, 15.0, 40.0, 0.0
    for step in range(600):
        next_lead = lead_v if step < 100 else max(0.0, lead_v - leader_deceleration * DT)
        acc = acceleration(v, gap, lead_v, params=params)
        next_v = max(0.0, v + acc * DT)
        gap += 0.5 * (lead_v + next_lead) * DT - 0.5 * (v + next_v) * DT
        lead_v, v, hardest = next_lead, next_v, max(hardest, -acc)
    return hardest


def test_a_leader_braking_as_estimated_never_makes_the_follower_brake_beyond_b_max():
    # Gipps' safety constraint: if the leader brakes at b_lead (the follower's estimate), the
    # follower stops in time braking at most b_max (3.37 of 3.4 here). Negative control: a leader
    # braking 20% harder than estimated forces harder braking (3.95).
    assert hardest_braking(HAND.b_lead) <= HAND.b_max + 0.01
    assert hardest_braking(1.2 * HAND.b_lead) > HAND.b_max + 0.3


def test_scene_generation_starts_platoons_at_the_gipps_equilibrium_gap():
    # v_safe = v with v_l = v, solved by hand from eq. (3):
    #   g = d_min + 1.5 v tau + v^2 (1/b_max - 1/b_lead) / 2;  v 12, tau 0.1, b 3, b-hat 5:
    #   g = 2 + 1.8 + 72 (1/3 - 1/5) = 2 + 1.8 + 9.6 = 13.4
    params = jax.tree.map(lambda x: jnp.full(3, x), HAND._replace(b_max=3.0, b_lead=5.0, sigma=0.0))
    gaps = np.asarray(equilibrium_gap(GIPPS, params, jnp.asarray(12.0), DT))
    np.testing.assert_allclose(gaps, 13.4, atol=1e-3)


# --- recovery: data from a simulator written here from the paper, not the model's sampler ---

TRUTH = {"v_des": 16.0, "a_max": 1.5, "b_max": 3.0, "b_lead": 3.0, "d_min": 2.5, "sigma": 0.2}
# b_lead is fixed at its truth: it enters only as b_max / b_lead times v_l^2, which a few
# braking episodes cannot tell apart from b_max.
FITTED = ("v_des", "a_max", "b_max", "d_min", "sigma")


def leader_speeds(num_steps: int) -> np.ndarray:
    """Cruise at 14 m/s, brake at 2.5 m/s^2, crawl, speed up, brake again: both branches used."""
    acc = np.zeros(num_steps)
    part = num_steps // 6
    acc[part : part + 40] = -2.5
    acc[3 * part : 3 * part + 60] = 1.5
    acc[5 * part : 5 * part + 30] = -2.0
    return np.maximum(0.0, 14.0 + np.cumsum(acc) * DT)


def simulate_paper(rng, num_steps: int, truth: dict, free_gain: float = 2.5) -> np.ndarray:
    """(steps, [v, next_v, dx, gap, lead_v]) of one noisy follower, in float64 numpy."""
    lead_v = leader_speeds(num_steps + 1)
    v, gap, rows = 10.0, 25.0, []
    b, b_hat = -truth["b_max"], -truth["b_lead"]
    for t in range(num_steps):
        free = paper_free_speed(v, truth["v_des"], truth["a_max"], DT, free_gain)
        safe = paper_safe_speed(v, lead_v[t], gap, b, b_hat, truth["d_min"], DT)
        target = max(0.0, min(free, np.nan_to_num(safe, nan=0.0)))
        acc = (target - v) / DT + truth["sigma"] * rng.standard_normal()
        next_v = max(0.0, v + acc * DT)
        dx = 0.5 * (v + next_v) * DT
        rows.append((v, next_v, dx, gap, lead_v[t]))
        gap += 0.5 * (lead_v[t] + lead_v[t + 1]) * DT - dx
        v = next_v
    return np.array(rows)


def as_arrays(series: list[np.ndarray]) -> FollowerArrays:
    r = np.stack(series)
    shape = r.shape[:2]
    return FollowerArrays(
        vehicle_ids=tuple(f"paper{i}" for i in range(len(series))),
        v=r[..., 0],
        next_v=r[..., 1],
        dx=r[..., 2],
        gap=r[..., 3],
        lead_v=r[..., 4],
        has_leader=np.ones(shape),
        mask=np.ones(shape),
        t=np.broadcast_to(np.arange(shape[1]) * DT, shape).copy(),
        dt=DT,
    )


def fitted_intervals(seed: int, arrays: FollowerArrays) -> dict[str, np.ndarray]:
    """Per parameter, (vehicle, [0.5%, 99.5%]) smc posterior quantiles."""
    result = smc.run(
        jax.random.key(seed),
        arrays,
        model=GIPPS,
        params=FITTED,
        fixed={"b_lead": TRUTH["b_lead"]},
        num_particles=400,
    )
    return {n: np.quantile(result.posterior[n][0], [0.005, 0.995], axis=0).T for n in FITTED}


def test_smc_recovers_the_parameters_of_an_independent_simulator():
    # Seeds: numpy 11 for the data, JAX key 12 for smc. Two followers x 50 s.
    rng = np.random.default_rng(11)
    arrays = as_arrays([simulate_paper(rng, 500, TRUTH) for _ in range(2)])
    intervals = fitted_intervals(12, arrays)
    for name, (low, high) in ((n, iv.T) for n, iv in intervals.items()):
        assert np.all((low <= TRUTH[name]) & (TRUTH[name] <= high)), (name, low, high)
        # Informative, so a truth outside would show: under a tenth of the prior width.
        spec = GIPPS.spec(name)
        assert np.all(high - low < 0.1 * (spec.upper - spec.lower)), (name, low, high)


def test_recovery_fails_when_the_simulator_disagrees_on_the_free_speed_law():
    # Negative control: a simulator with 2.0 a tau instead of Gipps' 2.5 a tau in the free speed
    # makes a_max's interval miss its truth (the fit finds about 2.0 / 2.5 of it).
    rng = np.random.default_rng(11)
    arrays = as_arrays([simulate_paper(rng, 500, TRUTH, free_gain=2.0) for _ in range(2)])
    low, high = fitted_intervals(12, arrays)["a_max"].T
    assert np.all((high < TRUTH["a_max"]) | (low > TRUTH["a_max"])), (low, high)


# --- the CLI: fit --model gipps with every engine but pmmh, on real data ---

runner = CliRunner()
CHAIN = "ngsim_i80_chains/124_136_140_146_162_164.csv"
# Warm-up cut for the NUTS-based engines so each run stays a few seconds (defaults: 500).
QUICK = {
    "nuts": functools.partial(nuts.run, num_warmup=50, num_chains=2),
    "hierarchical": functools.partial(hierarchical.run, num_warmup=50, num_chains=2),
}


# The MCMC engines' runs compile a program each (NUTS' tree builder, the hierarchical model) for
# about two minutes of CI on a slow machine: they are in the extended tier, and smc's command
# line too (its Gipps program is compiled again by the recovery test above, at its own sizes).
# CI keeps pf and lm on Gipps through the command line, smc on Gipps through the library, and
# nuts and emcee on the IDM and its extensions, all through the one likelihood that every engine
# reads a model by (reports/ci_time.md).
IN_EXTENDED = [
    pytest.param(engine, marks=pytest.mark.extended)
    for engine in ("smc", "nuts", "emcee", "hierarchical")
]


@pytest.mark.realdata
@pytest.mark.parametrize("engine", ["pf", "lm", *IN_EXTENDED])
def test_fit_model_gipps_runs_with_every_engine(data_dir, tmp_path, engine, monkeypatch):
    if engine in QUICK:
        monkeypatch.setitem(fit.ENGINES, engine, QUICK[engine])
    args = ["fit", str(data_dir / CHAIN), "--model", "gipps", "--engine", engine]
    vehicles = 2 if engine == "hierarchical" else 1  # a population needs two
    size = "--particles" if engine in ("smc", "pf") else "--draws"
    args += ["--vehicles", str(vehicles), size, "64", "--params", "v_des,b_max,sigma"]
    result = runner.invoke(app, [*args, "--seed", "4", "--out", str(tmp_path)])
    # 64 MCMC draws cannot pass the convergence checks: such a fit is written and exits 3.
    assert result.exit_code in ((0,) if engine in ("smc", "pf", "lm") else (0, 3)), result.output
    tree = load_result(tmp_path / "result.nc")
    meta = metadata(tree)
    assert (meta["model"], meta["engine"]) == ("gipps", engine)
    assert set(meta["fixed"]) == {"a_max", "b_lead", "d_min"}
    for name in ("v_des", "b_max", "sigma"):
        draws = tree["posterior"][name].values
        spec = GIPPS.spec(name)
        assert draws.shape[-1] == vehicles and np.all((spec.lower <= draws) & (draws <= spec.upper))


@pytest.mark.realdata
def test_pmmh_with_gipps_is_refused_in_one_line(data_dir, tmp_path):
    args = ["fit", str(data_dir / CHAIN), "--model", "gipps", "--engine", "pmmh"]
    result = runner.invoke(app, [*args, "--out", str(tmp_path)])
    assert result.exit_code == 2
    # One message (rich wraps it at the console width), naming the engine and the model.
    message = " ".join(result.stderr.split())
    assert message.count("error:") == 1 and "'pmmh'" in message and "'gipps'" in message
    assert not any(tmp_path.iterdir())


# --- criticize --model gipps: the extensions that fit the base model, the others refused ---


@pytest.fixture(scope="module")
def delayed_platoon(tmp_path_factory):
    """A small platoon from the independent generator (IDM drivers with a perception delay)."""
    from trafficgen import generate

    path = tmp_path_factory.mktemp("gipps") / "delay.csv"
    generate(
        5,
        path,
        {"perception_delay": (0.4, 0.7)},
        platoons=1,
        followers=3,
        duration_s=30.0,
        cut_ins=0,
    )
    return path


def criticize(path, *extra):
    args = ["criticize", str(path), "--format", "ngsim_raw", "--seed", "6", *extra]
    return runner.invoke(app, args)


@pytest.mark.parametrize(
    ("model", "causes", "message"),
    [
        ("gipps", "drifting_parameters", "model 'gipps' has no parameter 'tau'"),
        ("cidm", "reaction_delay", "the Cooperative IDM needs MergeInputs"),
        ("idm+obs_noise", "reaction_delay", "is a former name"),
    ],
)
def test_criticize_refuses_what_cannot_work_before_any_fit(delayed_platoon, model, causes, message):
    result = criticize(delayed_platoon, "--model", model, "--causes", causes)
    assert result.exit_code == 2
    assert message in " ".join(result.stderr.split())


@pytest.mark.extended
def test_criticize_runs_on_the_gipps_model(delayed_platoon):
    extra = ["--model", "gipps", "--causes", "reaction_delay", "--particles", "32"]
    result = criticize(delayed_platoon, *extra, "--rollouts", "2", "--json", "-")
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["verdict"] in ("reaction_delay", "none") or report["verdict"].startswith(
        "unexplained: "
    )
    assert set(report["base"]["posterior"]) == set(GIPPS.param_names)
