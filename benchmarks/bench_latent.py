"""The latent-state engine: filter speed, likelihood-estimate noise vs particles, PMMH convergence.

Three studies, each recorded with its settings and seed:

1. **Noise of the likelihood estimate.** On the simulated noisy-IDM data of the tests (two
   followers, 15 s, tau = 1.5 s, sigma_obs = 10 cm; other IDM parameters known), the sd over
   ``--replicates`` seeds of the state filter's log-likelihood estimate at the truth, for several
   state-particle counts N, with kappa = var * N / T (theory: var ~ kappa T / N). PMMH mixes best
   when that sd is about 1-1.7 nats (Doucet et al. 2015), which sets ``num_state_particles``.
   Also the speed of the filter in particle-steps per second (compilation excluded).
2. **PMMH from dispersed starts (simulated).** The same data, four chains per vehicle from prior
   draws, inferring (tau, sigma_obs): R-hat, bulk ESS, acceptance, and whether the truth is inside
   the 90 % interval.
3. **The filter on real data.** The first ``--vehicles`` sorted NGSIM I-80 vehicles without
   flagged samples, fitting windows only (the held-out window is never read): mean and sd of the
   log-likelihood estimate over 16 seeds at each vehicle's exact-state fit (the ``lm`` engine's
   estimate, IDM without measurement noise) for several sigma_obs and N.
4. **PMMH on real data.** The same vehicles, all six IDM parameters and sigma_obs from prior
   draws: convergence diagnostics. NGSIM positions are the integrated (EMD-smoothed) speed, so
   their noise about the model is largely model error, not sensor noise.

Writes ``reports/latent/bench_latent.md``, ``bench_latent.json`` and ``loglik_sd.png`` (or to
``--out``). Run: ``python benchmarks/bench_latent.py [--vehicles 4] [--seed 3]``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import matplotlib.ticker
import numpy as np

from bayesdrive.data.atomic import write_atomic, write_text_atomic
from bayesdrive.data.registry import load
from bayesdrive.data.views import FollowerArrays, follower_arrays
from bayesdrive.drivers.idm import IDM, IDMParams
from bayesdrive.drivers.measurement_noise import with_measurement_noise
from bayesdrive.inference.core.likelihood import fixed_params
from bayesdrive.inference.core.output import build_tree
from bayesdrive.inference.diagnostics.agreement import convergence_table
from bayesdrive.inference.diagnostics.synthetic_followers import simulate_following
from bayesdrive.inference.engines import lm
from bayesdrive.inference.engines.pmmh import (
    latent_data,
    noisy_readings,
    run,
    state_filter_loglik,
)

NOISY_IDM = with_measurement_noise(IDM)
TRUTH = {"tau": 1.5, "sigma_obs": 0.1}
SIM_NAMES = ("tau", "sigma_obs")
PARTICLE_COUNTS = (16, 32, 64, 128, 256, 512)
DATA = "ngsim_i80_chains"
REAL_PARTICLE_COUNTS = (64, 256, 1024)
REAL_SIGMA_OBS = (0.05, 0.2, 0.5)
REAL_SEEDS = 16


def simulated(key: jax.Array, num_vehicles: int, num_steps: int) -> tuple[FollowerArrays, dict]:
    """IDM followers (tau 1.5 s, other parameters at the defaults) read with 10 cm noise."""
    truth = NOISY_IDM.defaults()._replace(**{k: jnp.asarray(v) for k, v in TRUTH.items()})
    sim_key, noise_key = jax.random.split(key)
    vehicles = jax.tree.map(lambda a: jnp.full((num_vehicles,), a), IDMParams(*truth[:-1]))
    exact = simulate_following(sim_key, IDM, vehicles, num_steps=num_steps)
    known = {s.name: s.default for s in IDM.specs if s.name != "tau"}
    return noisy_readings(noise_key, exact, TRUTH["sigma_obs"]), known


def loglik_noise(key: jax.Array, arrays: FollowerArrays, known: dict, replicates: int) -> list:
    """sd of the filter's log-likelihood estimate at the truth, and speed, per particle count."""
    observations, inputs = latent_data(arrays, NOISY_IDM)
    params = fixed_params(NOISY_IDM, {**known, **TRUTH})
    rows = []
    for n in PARTICLE_COUNTS:

        def estimates(keys, n=n):
            def one_vehicle(k, obs, inp):
                return state_filter_loglik(k, NOISY_IDM, params, obs, inp, n)[0]

            per_seed = jax.vmap(one_vehicle, in_axes=(None, 0, 0))
            return jax.vmap(lambda k: per_seed(k, observations, inputs))(keys)

        keys = jax.random.split(jax.random.fold_in(key, n), replicates)
        compiled = jax.jit(estimates).lower(keys).compile()
        started = time.perf_counter()
        values = np.asarray(jax.block_until_ready(compiled(keys)), dtype=np.float64)
        seconds = time.perf_counter() - started
        steps = int(np.asarray(arrays.mask).sum())
        sd = values.std(axis=0, ddof=1)  # per vehicle
        rows.append(
            {
                "num_state_particles": n,
                "loglik_sd_per_vehicle": sd.tolist(),
                "kappa_per_vehicle": (sd**2 * n / arrays.mask.sum(axis=1)).tolist(),
                "particle_steps_per_s": replicates * steps * n / seconds,
            }
        )
    return rows


def real_filter_noise(key: jax.Array, arrays: FollowerArrays) -> list[dict]:
    """Mean and sd over seeds of the filter's log-likelihood at each vehicle's exact-state fit."""
    fit_key, filter_key = jax.random.split(key)
    exact_fit = lm.run(fit_key, arrays, model=IDM, num_particles=10)
    estimate = np.asarray(exact_fit.sample_stats["estimate"][1])  # (vehicle, IDM param)
    observations, inputs = latent_data(arrays, NOISY_IDM)
    rows = []
    for n in REAL_PARTICLE_COUNTS:
        for sigma_obs in REAL_SIGMA_OBS:
            theta = jnp.asarray(np.c_[estimate, np.full(len(estimate), sigma_obs)])

            def one(k, th, obs, inp, n=n):
                params = NOISY_IDM.params_type(*th)
                return state_filter_loglik(k, NOISY_IDM, params, obs, inp, n)[0]

            per_seed = jax.vmap(one, in_axes=(None, 0, 0, 0))
            keys = jax.random.split(jax.random.fold_in(filter_key, n), REAL_SEEDS)
            values = np.asarray(
                jax.jit(jax.vmap(lambda k, f=per_seed, th=theta: f(k, th, observations, inputs)))(
                    keys
                ),
                dtype=np.float64,
            )
            rows.append(
                {
                    "N": n,
                    "sigma_obs": sigma_obs,
                    "mean": values.mean(axis=0).round(1).tolist(),
                    "sd": values.std(axis=0, ddof=1).round(2).tolist(),
                }
            )
    return rows


def fitted_tree(key, arrays, names, fixed, seed, **options):
    """The pmmh engine on ``arrays`` and its result tree."""
    result = run(key, arrays, model=NOISY_IDM, params=names, fixed=fixed, **options)
    tree = build_tree(
        posterior=result.posterior,
        sample_stats=result.sample_stats,
        log_likelihood=result.log_likelihood,
        arrays=arrays,
        metadata={
            "engine": "pmmh",
            "model": NOISY_IDM.name,
            "params": list(names),
            "fixed": fixed,
            "seed": seed,
            "data_source": "benchmark",
            "window": "fit",
            "num_particles": options["num_particles"],
            "flagged_samples": None,
        },
    )
    return result, tree


def first_vehicles(traj, count: int) -> list[str]:
    """The first ``count`` sorted vehicle ids with no flagged sample (independent of any fit)."""
    flagged = set(traj.flags["vehicle_id"])
    candidates = sorted(v for v in traj.vehicle_ids if v not in flagged)
    usable = set(follower_arrays(traj, window="fit", vehicle_ids=candidates).vehicle_ids)
    return [v for v in candidates if v in usable][:count]


def markdown_table(rows: list[dict], columns: list[str]) -> str:
    def cell(value) -> str:
        return f"{value:.3g}" if isinstance(value, float) else str(value)

    lines = [" | ".join(columns), " | ".join("---" for _ in columns)]
    lines += [" | ".join(cell(row[c]) for c in columns) for row in rows]
    return "\n".join(f"| {line} |" for line in lines)


def convergence_rows(tree, truth: dict | None) -> list[dict]:
    table = convergence_table(tree)
    posterior = tree["posterior"].to_dataset()
    acceptance = tree["sample_stats"].to_dataset()["acceptance_rate"].values
    rows = []
    for record in table.to_dict("records"):
        vehicle = list(posterior["vehicle"].values).index(record["vehicle"])
        draws = posterior[record["param"]].values[:, :, vehicle].ravel()
        q05, q50, q95 = np.quantile(draws, [0.05, 0.5, 0.95])
        row = {
            "vehicle": str(record["vehicle"]),
            "param": record["param"],
            "median": float(q50),
            "q05": float(q05),
            "q95": float(q95),
            "rhat": float(record["rhat"]),
            "ess_bulk": float(record["ess_bulk"]),
            "acceptance": float(acceptance[:, vehicle].mean()),
        }
        if truth is not None:
            row["truth_in_90"] = bool(q05 <= truth[record["param"]] <= q95)
        rows.append(row)
    return rows


def plot_noise(rows: list[dict], path: Path) -> None:
    counts = np.array([r["num_state_particles"] for r in rows])
    sd = np.array([r["loglik_sd_per_vehicle"] for r in rows])
    fig, ax = plt.subplots(figsize=(5.5, 4))
    for vehicle in range(sd.shape[1]):
        ax.loglog(counts, sd[:, vehicle], "o-", label=f"simulated vehicle {vehicle}")
    # The 1/sqrt(N) line through the geometric mean of all points.
    level = np.exp(np.mean(np.log(sd) + 0.5 * np.log(counts)[:, None]))
    ax.loglog(counts, level / np.sqrt(counts), "k--", label=r"$\propto 1/\sqrt{N}$")
    ax.axhspan(1.0, 1.7, color="0.9", label="PMMH sweet spot (1-1.7)")
    ax.set_xticks(counts, labels=[str(c) for c in counts])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    top = max(sd.max(), 1.7)
    ticks = [t for t in (0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0) if sd.min() / 2 <= t <= top * 2]
    ax.set_yticks(ticks, labels=[f"{t:g}" for t in ticks])
    ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("state particles N")
    ax.set_ylabel("sd of the log-likelihood estimate (nats)")
    ax.set_title("State filter at the truth, 150 steps")
    ax.legend(fontsize=8)
    fig.tight_layout()
    write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=120, format="png"))
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--replicates", type=int, default=64)
    parser.add_argument("--vehicles", type=int, default=4)
    parser.add_argument("--warmup", type=int, default=1500)
    parser.add_argument("--draws", type=int, default=1000, help="per chain")
    parser.add_argument("--state-particles", type=int, default=64)
    parser.add_argument("--out", type=Path, default=Path("reports/latent"))
    args = parser.parse_args()
    load_before = os.getloadavg()
    key = jax.random.key(args.seed)
    data_key, noise_key, sim_key, real_noise_key, real_key = jax.random.split(key, 5)
    report: dict = {"seed": args.seed, "settings": vars(args) | {"out": str(args.out)}}

    arrays, known = simulated(data_key, num_vehicles=2, num_steps=150)
    report["loglik_noise"] = loglik_noise(noise_key, arrays, known, args.replicates)

    chains = 4
    pmmh_options = {
        "num_particles": chains * args.draws,
        "num_chains": chains,
        "num_warmup": args.warmup,
        "num_state_particles": args.state_particles,
        "init": "prior",
    }
    started = time.perf_counter()
    sim_result, sim_tree = fitted_tree(
        sim_key, arrays, SIM_NAMES, known, args.seed, proposal_scale=0.01, **pmmh_options
    )
    report["simulated_pmmh"] = {
        "seconds": time.perf_counter() - started,
        "compile_s": sim_result.compile_time_s,
        "rows": convergence_rows(sim_tree, TRUTH),
    }

    traj = load(DATA)
    vehicles = first_vehicles(traj, args.vehicles)
    real = follower_arrays(traj, window="fit", vehicle_ids=vehicles)
    report["real_filter_noise"] = real_filter_noise(real_noise_key, real)
    started = time.perf_counter()
    real_result, real_tree = fitted_tree(
        real_key, real, NOISY_IDM.param_names, {}, args.seed, proposal_scale=0.005, **pmmh_options
    )
    report["real_pmmh"] = {
        "data": DATA,
        "vehicles": vehicles,
        "usable_steps": int(real.mask.sum()),
        "seconds": time.perf_counter() - started,
        "compile_s": real_result.compile_time_s,
        "rows": convergence_rows(real_tree, None),
    }
    report["load_average"] = {"before": load_before, "after": os.getloadavg()}

    args.out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out / "bench_latent.json", json.dumps(report, indent=2) + "\n")
    plot_noise(report["loglik_noise"], args.out / "loglik_sd.png")
    noise_rows = [
        {
            "N": r["num_state_particles"],
            "sd (vehicle 0, 1)": ", ".join(f"{s:.2f}" for s in r["loglik_sd_per_vehicle"]),
            "kappa (vehicle 0, 1)": ", ".join(f"{k:.2f}" for k in r["kappa_per_vehicle"]),
            "particle-steps/s": r["particle_steps_per_s"],
        }
        for r in report["loglik_noise"]
    ]
    columns = ["vehicle", "param", "median", "q05", "q95", "rhat", "ess_bulk", "acceptance"]
    text = [
        "# Latent-state engine (state filter + PMMH)",
        "",
        f"Seed {args.seed}; load average before {load_before[0]:.1f}, after "
        f"{report['load_average']['after'][0]:.1f} (2 shared cores: timings are indicative).",
        "",
        "## 1. Log-likelihood estimate at the truth (simulated, 150 steps per vehicle)",
        "",
        f"{args.replicates} seeds per particle count. kappa = var * N / T.",
        "",
        markdown_table(noise_rows, list(noise_rows[0])),
        "",
        "![sd vs N](loglik_sd.png)",
        "",
        "## 2. PMMH from prior draws, simulated data (tau, sigma_obs; truth 1.5 s, 0.1 m)",
        "",
        f"4 chains x {args.draws} draws after {args.warmup} warm-up iterations, "
        f"{args.state_particles} state particles; {report['simulated_pmmh']['seconds']:.0f} s "
        f"(compile {report['simulated_pmmh']['compile_s']:.0f} s).",
        "",
        markdown_table(report["simulated_pmmh"]["rows"], [*columns, "truth_in_90"]),
        "",
        f"## 3. The filter on {DATA} at each vehicle's exact-state fit (lm), fitting windows",
        "",
        f"Vehicles {', '.join(vehicles)}; log-likelihood estimate over {REAL_SEEDS} seeds, per "
        "vehicle (in that order).",
        "",
        markdown_table(
            [
                {
                    "N": r["N"],
                    "sigma_obs": r["sigma_obs"],
                    "mean": ", ".join(f"{m:.0f}" for m in r["mean"]),
                    "sd": ", ".join(f"{x:.1f}" for x in r["sd"]),
                }
                for r in report["real_filter_noise"]
            ],
            ["N", "sigma_obs", "mean", "sd"],
        ),
        "",
        f"## 4. PMMH on {DATA}: all six IDM parameters + sigma_obs, fitting windows",
        "",
        f"Vehicles {', '.join(vehicles)} ({report['real_pmmh']['usable_steps']} usable steps); "
        f"same settings; {report['real_pmmh']['seconds']:.0f} s "
        f"(compile {report['real_pmmh']['compile_s']:.0f} s).",
        "",
        markdown_table(report["real_pmmh"]["rows"], columns),
        "",
    ]
    write_text_atomic(args.out / "bench_latent.md", "\n".join(text))
    print("\n".join(text))


if __name__ == "__main__":
    main()
