"""Peers in one run: bayesdrive's ``smc`` against BlackJAX's adaptive tempered SMC and NumPyro's NUTS.

The problem is ``bench_agreement``'s: NGSIM I-80 (``ngsim_i80_chains``) vehicles 124 and 140,
fitting windows, all six IDM parameters, the uniform prior box. Every sampler targets one
density, built from the library's own functions: the per-vehicle log-likelihood
(:func:`~bayesdrive.inference.core.likelihood.series_loglik`) plus the log prior, on the logit scale
of the prior box with its Jacobian (:mod:`bayesdrive.inference.core.kernels`, as smc's moves use).

* ``smc``: the engine at its defaults, ``--particles`` swept, ``--replicates`` independent
  replicates (the Monte Carlo error of a mean is their spread);
* ``blackjax``: ``blackjax.adaptive_tempered_smc`` (target ESS 0.5, smc's ``ess_threshold``) with
  BlackJAX's additive-step random walk, its Gaussian step the particles' covariance on the logit
  scale times (2.38 / sqrt d)^2 (smc's starting scale; re-estimated after every stage, as
  ``blackjax.inner_kernel_tuning`` does), ``--blackjax-moves`` moves a stage (smc's
  ``temper_moves``), the same particle counts and as many independent runs as smc has
  replicates; ``--blackjax-adapt`` moves each particle's scale after every stage towards an
  acceptance of 0.234 (BlackJAX's ``update_scale_from_acceptance_rate``; smc adapts one scale
  after every move). The particles leave the last stage weighted, so they are resampled once
  (systematic) into equal draws;
* ``nuts``: bayesdrive's ``nuts`` engine (NumPyro; its uniform box on NumPyro's logit-of-box
  scale with the Jacobian, the same density), 4 chains, ``--draws`` per chain swept after the
  engine's default warm-up.

Each setting is timed in one process, compilation apart (the engines' own timers; BlackJAX's
program is compiled ahead of time), with the 1-minute load average before it. Settings run
level by level (smc, blackjax, nuts at the first level, then the second ...), so a change of the
machine's background load falls on all three alike.

**Agreement** with the long NUTS reference runs (400,000 draws a vehicle), read from the committed
table ``reports/agreement/reference.md`` (its ``nuts (reference)`` rows: mean, sd and Monte Carlo
standard error), by the criterion of :mod:`bayesdrive.inference.diagnostics.agreement` (``CRITERION``, with its
constants): for every parameter of both vehicles, the means within max(0.1 pooled sd, 3 combined
standard errors) and the sds within 10%. The library's ``agreement_table`` compares two sets of
draws; the reference is a table of summaries, so the criterion is applied here to the summaries.
A sampler's standard errors are :func:`~bayesdrive.inference.diagnostics.agreement.mcse_mean`'s (replicate
spread for the particle samplers, ArviZ's for NUTS chains).

Writes ``reports/peers/runs.csv`` (one row per sampler, setting and vehicle) and
``reports/peers/table.md`` (one row per sampler and setting, and the least time at which each
sampler agrees). Run under ``nice``: ``python benchmarks/bench_peers.py [--seed 17]``; a quick
check: ``--particles 100 --draws 100 --replicates 2``; other BlackJAX settings alone:
``--samplers blackjax --blackjax-moves 100 --out reports/peers/blackjax_100_moves``.
"""

from __future__ import annotations

import argparse
import os
import re
import time
from pathlib import Path

import blackjax
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import xarray as xr

# bench_agreement sits beside this file (benchmarks/ is on sys.path when run as a script).
from bench_agreement import markdown
from blackjax.smc.base import extend_params
from blackjax.smc.resampling import systematic
from blackjax.smc.tuning.from_kernel_info import update_scale_from_acceptance_rate
from blackjax.smc.tuning.from_particles import particles_covariance_matrix

from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.data.registry import load
from bayesdrive.data.views import follower_arrays
from bayesdrive.drivers.idm import IDM
from bayesdrive.inference.core.kernels import Box, from_free, log_jacobian, to_free
from bayesdrive.inference.core.likelihood import series_loglik
from bayesdrive.inference.core.output import set_metadata
from bayesdrive.inference.core.vehicles import (
    VehicleProblem,
    posterior_draws,
    prepare,
    vehicle_keys,
)
from bayesdrive.inference.diagnostics.agreement import CRITERION, judge, mcse_mean, mcse_sd
from bayesdrive.inference.engines import nuts, smc

DATA = "ngsim_i80_chains"
REFERENCE = Path("reports/agreement/reference.md")
REFERENCE_ENGINE = "nuts (reference)"
NUTS_CHAINS = 4
# smc's starting random-walk scale (Roberts, Gelman & Gilks 1997), kept fixed for BlackJAX.
RW_SCALE = 2.38
# smc's floor on the proposal covariance, for the same reason: a stage that leaves few distinct
# particles must not leave a singular covariance.
JITTER = 1e-6


def read_reference(path: Path) -> pd.DataFrame:
    """The ``nuts (reference)`` rows of the committed reference table: vehicle, param, mean, sd,
    se."""
    rows = []
    for line in path.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 7 and cells[1] == REFERENCE_ENGINE:
            vehicle, _, param, mean, sd, se, _ = cells
            rows.append((vehicle, param, float(mean), float(sd), float(se)))
    if not rows:
        raise ValueError(f"no {REFERENCE_ENGINE!r} rows in {path}")
    return pd.DataFrame(rows, columns=["vehicle", "param", "mean", "sd", "se"])


def logit_density(problem: VehicleProblem):
    """The one vehicle's target on u = logit of the prior box: (box, log prior with the
    Jacobian, log-likelihood), each of one u (d,)."""
    box = Box(problem.box.lower, problem.box.upper)
    series = jax.tree.map(lambda a: a[0], problem.series)

    def log_prior(u):
        return problem.prior.logpdf(from_free(u, box)) + log_jacobian(u, box)

    def log_lik(u):
        theta = from_free(u, box)
        return series_loglik(problem.model, problem.names, problem.fixed, theta, series).sum()

    return box, log_prior, log_lik


def blackjax_run(problem: VehicleProblem, num_particles: int, num_moves: int, adapt: bool):
    """One adaptive tempered SMC run (module docstring) as a function of its key: equally
    weighted draws (N, d) on the parameter scale and the number of tempering stages.

    The walk's step is the particles' covariance times (2.38 / sqrt d)^2, times a scale per
    particle: 1, or with ``adapt`` moved after every stage by BlackJAX's
    ``update_scale_from_acceptance_rate`` towards an acceptance of 0.234."""
    box, log_prior, log_lik = logit_density(problem)
    dim = len(problem.names)
    walk = blackjax.additive_step_random_walk.build_kernel()

    def move(key, state, logdensity_fn, chol, scale):
        # The step is a function, which SMC cannot broadcast over particles: its Cholesky factor
        # and scale travel as the parameters instead.
        return walk(key, state, logdensity_fn, blackjax.mcmc.random_walk.normal(scale * chol))

    def parameters(particles, scale):
        cov = particles_covariance_matrix(particles) + JITTER * jnp.eye(dim)
        chol = RW_SCALE / np.sqrt(dim) * jnp.linalg.cholesky(cov)
        return {"chol": extend_params(chol), "scale": scale}

    def run(key):
        key_init, key_loop, key_draws = jax.random.split(key, 3)
        u = to_free(problem.prior.sample(key_init, (num_particles,)), box)
        # One shared scale (leading axis 1) unless each particle adapts its own.
        scale = jnp.ones(num_particles if adapt else 1, u.dtype)

        def stage(carry):
            state, params, key, stages = carry
            key, key_stage = jax.random.split(key)
            # As blackjax.inner_kernel_tuning does (the same keys): a step built with this
            # stage's parameters. Its update function sees no earlier parameters, which the
            # adapted scale needs, so the loop is written out here.
            _, key_step = jax.random.split(key_stage)
            sampler = blackjax.adaptive_tempered_smc(
                logprior_fn=log_prior,
                loglikelihood_fn=log_lik,
                mcmc_step_fn=move,
                mcmc_init_fn=blackjax.additive_step_random_walk.init,
                mcmc_parameters=params,
                resampling_fn=systematic,
                target_ess=0.5,
                num_mcmc_steps=num_moves,
            )
            state, info = sampler.step(key_step, state)
            scale = params["scale"]
            if adapt:
                acceptance = info.update_info.acceptance_rate.mean(axis=1)
                scale = update_scale_from_acceptance_rate(scale, acceptance)
            return state, parameters(state.particles, scale), key, stages + 1

        state, _, _, stages = jax.lax.while_loop(
            lambda carry: carry[0].tempering_param < 1.0,
            stage,
            (
                blackjax.adaptive_tempered_smc.init(u),
                parameters(u, scale),
                key_loop,
                jnp.zeros((), jnp.int32),
            ),
        )
        chosen = systematic(key_draws, state.weights, num_particles)
        return from_free(state.particles[chosen], box), stages

    return run


def posterior_tree(posterior: dict[str, np.ndarray], vehicle: str, replicates: int) -> xr.DataTree:
    """Draws name -> (chain, draw, 1) as a result tree that ``mcse_mean`` reads: chains are
    independent replicates when ``replicates`` > 1."""
    dims = ("chain", "draw", "vehicle")
    dataset = xr.Dataset(
        {name: (dims, values) for name, values in posterior.items()}, coords={"vehicle": [vehicle]}
    )
    tree = xr.DataTree.from_dict({"posterior": dataset})
    set_metadata(tree, engine_options={"replicates": replicates})
    return tree


def against_reference(tree: xr.DataTree, vehicle: str, reference: pd.DataFrame) -> list[dict]:
    """Per parameter: this run's mean, sd and standard error beside the reference's, and the
    criterion's verdict (module docstring)."""
    posterior = tree["posterior"].to_dataset()
    mcse, sd_mcse = mcse_mean(tree), mcse_sd(tree)
    rows = []
    for ref in reference[reference["vehicle"] == vehicle].itertuples():
        draws = np.asarray(posterior[ref.param].values, dtype=np.float64).ravel()
        mean, sd = draws.mean(), draws.std()
        se = float(mcse[ref.param].sel(vehicle=vehicle))
        sd_se = float(sd_mcse[ref.param].sel(vehicle=vehicle))
        # The reference table holds no sd error: it counts as 0 (the stricter side).
        verdict = judge(ref.mean, ref.sd, ref.se, mean, sd, se, mcse_sd_a=0.0, mcse_sd_b=sd_se)
        rows.append(
            {
                "param": ref.param,
                "mean": mean,
                "sd": sd,
                "se": se,
                "mean_error_tol": abs(mean - ref.mean) / verdict.tolerance,
                "sd_ratio": sd / ref.sd,
                "agree": verdict.agree_mean and verdict.agree_sd,
            }
        )
    return rows


def run_smc(key, arrays, vehicle, particles, replicates):
    result = smc.run(key, arrays, model=IDM, num_particles=particles, replicates=replicates)
    tree = posterior_tree(result.posterior, vehicle, replicates)
    return tree, result.compile_time_s, result.wall_time_s, {}


def run_blackjax(key, problem, vehicle, particles, replicates, moves, adapt):
    keys = vehicle_keys(key, [vehicle], replicates)[:, 0]
    started = time.perf_counter()
    compiled = jax.jit(blackjax_run(problem, particles, moves, adapt)).lower(keys[0]).compile()
    compile_time = time.perf_counter() - started
    draws, stages, run_time = [], [], 0.0
    for replicate_key in keys:
        started = time.perf_counter()
        theta, count = jax.block_until_ready(compiled(replicate_key))
        run_time += time.perf_counter() - started
        draws.append(np.asarray(theta))
        stages.append(int(count))
    posterior = posterior_draws(problem.names, np.stack(draws)[None])
    tree = posterior_tree(posterior, vehicle, replicates)
    return tree, compile_time, run_time, {"stages": stages}


def run_nuts(key, arrays, vehicle, draws_per_chain):
    result = nuts.run(
        key, arrays, model=IDM, num_particles=NUTS_CHAINS * draws_per_chain, num_chains=NUTS_CHAINS
    )
    diverging = int(result.sample_stats["diverging"][1].sum())
    tree = posterior_tree(result.posterior, vehicle, 1)
    return tree, result.compile_time_s, result.wall_time_s, {"divergences": diverging}


def integers(text: str) -> list[int]:
    return [int(v) for v in re.split(r"[,\s]+", text.strip()) if v]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", default="124,140")
    parser.add_argument("--seed", type=int, default=17)
    parser.add_argument("--particles", default="250,500,1000,2000")
    parser.add_argument("--draws", default="500,1000,2000,4000", help="NUTS draws per chain")
    parser.add_argument("--replicates", type=int, default=4)
    parser.add_argument("--blackjax-moves", type=int, default=20)
    parser.add_argument(
        "--blackjax-adapt", action="store_true", help="adapt each particle's random-walk scale"
    )
    parser.add_argument("--samplers", default="smc,blackjax,nuts")
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--reference", type=Path, default=REFERENCE)
    parser.add_argument("--out", type=Path, default=Path("reports/peers"))
    args = parser.parse_args(argv)

    reference = read_reference(args.reference)
    vehicles = args.vehicles.split(",")
    traj = load(DATA, data_dir=args.data_dir)
    arrays = {v: follower_arrays(traj, window="fit", vehicle_ids=[v]) for v in vehicles}
    problems = {
        v: prepare("smc", a, model=IDM, params=None, fixed=None, prior=None)
        for v, a in arrays.items()
    }

    particles, draws = integers(args.particles), integers(args.draws)
    if len(particles) != len(draws):
        raise ValueError("--particles and --draws need as many levels (they run level by level)")
    key = jax.random.key(args.seed)
    runners = {
        "smc": lambda vehicle, level: run_smc(
            key, arrays[vehicle], vehicle, particles[level], args.replicates
        ),
        "blackjax": lambda vehicle, level: run_blackjax(
            key,
            problems[vehicle],
            vehicle,
            particles[level],
            args.replicates,
            args.blackjax_moves,
            args.blackjax_adapt,
        ),
        "nuts": lambda vehicle, level: run_nuts(key, arrays[vehicle], vehicle, draws[level]),
    }
    settings = {
        "smc": [f"{n} particles x {args.replicates} replicates" for n in particles],
        "blackjax": [f"{n} particles x {args.replicates} runs" for n in particles],
        "nuts": [f"{NUTS_CHAINS} chains x {n} draws" for n in draws],
    }
    samplers = args.samplers.split(",")
    rows = []
    for level in range(len(particles)):
        for sampler in samplers:
            for vehicle in vehicles:
                load_before = os.getloadavg()[0]
                tree, compile_s, run_s, extras = runners[sampler](vehicle, level)
                checks = against_reference(tree, vehicle, reference)
                for check in checks:
                    rows.append(
                        {
                            "sampler": sampler,
                            "level": level,
                            "setting": settings[sampler][level],
                            "vehicle": vehicle,
                            "run_s": run_s,
                            "compile_s": compile_s,
                            "load_1min": load_before,
                            **check,
                            **{k: str(v) for k, v in extras.items()},
                        }
                    )
                agreed = sum(c["agree"] for c in checks)
                print(
                    f"{sampler} {settings[sampler][level]} vehicle {vehicle}: {run_s:.1f} s "
                    f"(+{compile_s:.1f} s compile, load {load_before:.2f}), "
                    f"{agreed}/{len(checks)} agree {extras}",
                    flush=True,
                )

    runs = pd.DataFrame(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out / "runs.csv", runs.to_csv(index=False))

    per_vehicle = runs.groupby(["sampler", "level", "setting", "vehicle"], sort=False).agg(
        run_s=("run_s", "first"),
        compile_s=("compile_s", "first"),
        load=("load_1min", "first"),
        agree=("agree", "sum"),
        checks=("agree", "size"),
        worst_mean=("mean_error_tol", "max"),
        worst_sd=("sd_ratio", lambda r: float(np.max(np.maximum(r, 1 / r)))),
    )
    table = (
        per_vehicle.groupby(["sampler", "level", "setting"], sort=False)
        .agg(
            run_s=("run_s", "sum"),
            compile_s=("compile_s", "sum"),
            load=("load", "mean"),
            agree=("agree", "sum"),
            checks=("checks", "sum"),
            worst_mean=("worst_mean", "max"),
            worst_sd=("worst_sd", "max"),
        )
        .reset_index()
    )
    table["agrees"] = table["agree"] == table["checks"]
    shown = table.assign(agree=table["agree"].astype(str) + "/" + table["checks"].astype(str)).drop(
        columns=["level", "checks"]
    )
    shown = shown.rename(
        columns={
            "run_s": "run (s, both vehicles)",
            "compile_s": "compile (s)",
            "load": "load avg",
            "agree": "checks passed",
            "worst_mean": "worst mean error / tolerance",
            "worst_sd": "worst sd ratio",
        }
    )
    least = []
    for sampler in samplers:
        ok = table[(table["sampler"] == sampler) & table["agrees"]]
        least.append(
            f"- {sampler}: "
            + (
                f"{ok['run_s'].min():.1f} s ({ok.loc[ok['run_s'].idxmin(), 'setting']})"
                if len(ok)
                else "did not agree"
            )
        )
    lines = [
        "# Peers (benchmarks/bench_peers.py)",
        "",
        f"{DATA} vehicles {', '.join(vehicles)}, fitting windows, all six IDM parameters, uniform "
        f"prior box; seed {args.seed}; BlackJAX {blackjax.__version__}, {args.blackjax_moves} "
        f"moves a stage, {'adapted' if args.blackjax_adapt else 'fixed'} random-walk scale. "
        "Agreement with the reference "
        f"({args.reference}, {REFERENCE_ENGINE}): {CRITERION}, for every parameter of every "
        "vehicle (checks passed counts them). Run times exclude compilation; load avg is the "
        "1-minute load average before each run.",
        "",
        markdown(shown, "{:.3g}"),
        "",
        "Least run time at which each sampler agrees:",
        "",
        *least,
        "",
    ]
    write_text_atomic(args.out / "table.md", "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
