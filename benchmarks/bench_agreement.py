"""Do the engines agree on real data? smc vs nuts vs emcee (and the paper's pf) on NGSIM I-80.

Vehicles (fixed rule, chosen before any fit): the first ``--vehicles`` (default 15) vehicle ids of
``ngsim_i80_chains`` in sorted order that have no flagged sample; each is fitted on its own
fitting window (the split rule of :mod:`bayesdrive.data.views`), all six IDM parameters, the
same uniform prior box and the same likelihood in every engine. The held-out data is never read.

Writes to ``reports/agreement/`` (or ``--out``): ``agreement.md`` (settings, runtimes, NUTS
divergences, the per-pair agreement summary and every failing vehicle), ``agreement.csv``,
``convergence_<engine>.csv``, ``agreement_heatmap.png`` and ``marginals_<param>.png``.
pf is the paper's filter: its departures are reported, not hidden.

``--nuts-batch`` also times nuts with all vehicles vectorised in one batch against one vehicle
at a time (short runs), the design choice documented in :mod:`bayesdrive.inference.engines.nuts`.

Run: ``python benchmarks/bench_agreement.py [--vehicles 15] [--seed 7]``; ``--model NAME`` fits
another model (an extension's parameters too) into ``reports/agreement/<model>/``, and
``--nuts-draws`` / ``--smc-replicates`` shorten the runs (the criterion accounts for the larger
Monte Carlo error, so it stays a fair test, with less power).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import numpy as np
import pandas as pd

from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.data.registry import load
from bayesdrive.data.views import follower_arrays
from bayesdrive.drivers.idm import IDM
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.core.output import metadata
from bayesdrive.inference.diagnostics.agreement import (
    CRITERION,
    agreement_summary,
    agreement_table,
    convergence_table,
)
from bayesdrive.inference.engines import nuts
from bayesdrive.inference.fit import fit
from bayesdrive.reports.diagnostic_plots import plot_agreement_heatmap, plot_marginals

DATA = "ngsim_i80_chains"
# Long runs: the agreement criterion needs Monte Carlo error well below 0.1 posterior sd (means)
# and well below 10% (sds), and an ESS of at least 1000 for every vehicle and parameter (nuts: bulk
# and tail ESS; smc: from the spread of its independent replicates, see
# bayesdrive.inference.diagnostics.agreement.mcse_mean). 8 smc replicates gave a minimum of 500 (vehicle 11),
# hence 20. nuts: a dense mass matrix lifted the worst tail ESS of vehicle 124 but met 467
# divergences on vehicle 11 and 217 on vehicle 112 and went narrow on vehicle 11 (diagonal, 8000
# draws: 31 divergences in all), so the mass matrix is diagonal. Vehicle 124's a_max and b_pref
# sds rest on rare visits to a b_pref tail (P(b_pref > 3.5) about 0.015): at 32000 draws four
# seeds gave an a_max sd of 0.065-0.080 (reference 0.073, bench_reference.py), so the sd alone
# was off by up to 12%; 128000 draws halve that. emcee: the kept run (num_steps - num_burn) must
# exceed 50 autocorrelation times; the slowest vehicles reached tau of 1400-1800 steps, and
# at 60000 kept steps vehicle 124's a_max sd still varied by 5% between seeds, hence 125000.
ENGINE_OPTIONS = {
    "smc": {"num_particles": 1000, "replicates": 20},
    "nuts": {"num_particles": 128000, "num_chains": 4, "num_warmup": 2000, "dense_mass": False},
    "emcee": {"num_particles": 4000, "num_steps": 130000, "num_burn": 5000},
    "pf": {"num_particles": 4000},
}


def markdown(frame: pd.DataFrame, float_format: str = "{:.3f}") -> str:
    """A pipe table; floats as ``float_format`` (3 decimals by default)."""

    def cell(value) -> str:
        return float_format.format(value) if isinstance(value, float | np.floating) else str(value)

    rows = [" | ".join(map(str, frame.columns)), " | ".join("---" for _ in frame.columns)]
    rows += [" | ".join(cell(v) for v in row) for row in frame.itertuples(index=False)]
    return "\n".join(f"| {row} |" for row in rows)


def mean_log_likelihood(trees) -> pd.DataFrame:
    """Per vehicle (rows) and engine (columns): the mean over posterior draws of the summed
    log-likelihood. Where engines disagree, the one far below the others sits in a poorer region
    (under a flat prior the posterior mass follows the likelihood)."""
    return pd.DataFrame(
        {
            engine: tree["log_likelihood"]["dx"]
            .groupby("vehicle")
            .sum()
            .mean(("chain", "draw"))
            .to_series()
            for engine, tree in trees.items()
        }
    )


def choose_vehicles(traj, count: int) -> list[str]:
    """The first ``count`` sorted vehicle ids with no flagged sample (independent of any fit)."""
    flagged = set(traj.flags["vehicle_id"])
    candidates = sorted(v for v in traj.vehicle_ids if v not in flagged)
    usable = set(follower_arrays(traj, window="fit", vehicle_ids=candidates).vehicle_ids)
    return [v for v in candidates if v in usable][:count]


def nuts_batch_timing(key, arrays) -> dict[str, float]:
    """Wall time (compile excluded) of short nuts runs: one vehicle at a time vs all at once."""
    timings = {}
    for batch in (1, len(arrays.vehicle_ids)):
        result = nuts.run(
            key,
            arrays,
            model=IDM,
            num_particles=800,
            num_warmup=200,
            vehicle_batch=batch,
            vehicle_chunk=len(arrays.vehicle_ids),
        )
        timings[f"vehicle_batch={batch}"] = result.wall_time_s
        timings[f"vehicle_batch={batch} compile"] = result.compile_time_s
    return timings


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", type=int, default=15)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--engines", default="smc,nuts,emcee,pf")
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--nuts-batch", action="store_true")
    parser.add_argument("--out", type=Path, default=None, help="default: reports/agreement")
    parser.add_argument("--model", default="idm")
    parser.add_argument("--nuts-draws", type=int, default=ENGINE_OPTIONS["nuts"]["num_particles"])
    parser.add_argument("--smc-replicates", type=int, default=ENGINE_OPTIONS["smc"]["replicates"])
    args = parser.parse_args(argv)
    model = get_model(args.model)
    if args.out is None:
        args.out = Path("reports/agreement") / ("" if model is IDM else model.name)
    options = {
        **ENGINE_OPTIONS,
        "smc": {**ENGINE_OPTIONS["smc"], "replicates": args.smc_replicates},
        "nuts": {**ENGINE_OPTIONS["nuts"], "num_particles": args.nuts_draws},
    }

    traj = load(DATA, data_dir=args.data_dir)
    vehicles = choose_vehicles(traj, args.vehicles)
    # Arrays, not a subset: a subset would drop the leaders whose speeds the followers need.
    arrays = follower_arrays(traj, window="fit", vehicle_ids=vehicles)
    trees, runtimes = {}, {}
    for engine in args.engines.split(","):
        started = time.perf_counter()
        trees[engine] = fit(
            jax.random.key(args.seed),
            arrays,
            model=model,
            engine=engine,
            seed=args.seed,
            **options[engine],
        )
        runtimes[engine] = time.perf_counter() - started
        print(f"{engine}: {runtimes[engine]:.0f} s", flush=True)

    table = agreement_table(trees)
    summary = agreement_summary(table)
    args.out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out / "agreement.csv", table.to_csv(index=False))
    convergence = {}
    for engine, tree in trees.items():
        convergence[engine] = convergence_table(tree)
        write_text_atomic(
            args.out / f"convergence_{engine}.csv", convergence[engine].to_csv(index=False)
        )
    plot_agreement_heatmap(table, args.out / "agreement_heatmap.png")
    plot_marginals(trees, args.out)

    lines = [
        "# Engine agreement on NGSIM I-80 (benchmarks/bench_agreement.py)",
        "",
        f"{len(vehicles)} vehicles ({', '.join(vehicles)}): the first sorted ids of {DATA} "
        f"without flagged samples; fitting windows only ({int(arrays.mask.sum())} steps in all); "
        f"model {model.name}, all its parameters ({', '.join(model.param_names)}), uniform "
        f"prior box; seed {args.seed}.",
        "",
        f"Engine settings: `{json.dumps({e: options[e] for e in args.engines.split(',')})}`",
        "",
        "Runtimes (s, compilation included): "
        + ", ".join(f"{e} {s:.0f}" for e, s in runtimes.items()),
        "",
    ]
    if "nuts" in convergence:
        table_nuts = convergence["nuts"]
        divergences = table_nuts.groupby("vehicle")["divergences"].first()
        options = metadata(trees["nuts"])["engine_options"]
        mass = "dense" if options["dense_mass"] else "diagonal"
        lines += [
            f"NUTS ({mass} mass matrix, adapted per vehicle and chain): "
            f"{int(divergences.sum())} divergent transitions over {len(divergences)} vehicles "
            f"(target_accept_prob {options['target_accept_prob']}); max R-hat "
            f"{table_nuts['rhat'].max():.3f}; "
            f"min bulk ESS {table_nuts['ess_bulk'].min():.0f}; min tail ESS "
            f"{table_nuts['ess_tail'].min():.0f}.",
            "",
        ]
    if "smc" in convergence:
        table_smc = convergence["smc"]
        stages = trees["smc"]["sample_stats"]["temper_stages"].values
        lines += [
            f"smc: {metadata(trees['smc'])['engine_options']['replicates']} independent "
            f"replicates; min ESS of the mean (posterior variance / MCSE^2 from the replicates' "
            f"spread) {table_smc['ess_mean'].min():.0f}; max R-hat across replicates "
            f"{table_smc['rhat'].max():.3f}; closing tempering stages {stages.min()}-"
            f"{stages.max()}.",
            "",
        ]
    if "emcee" in convergence:
        table_emcee = convergence["emcee"]
        lines += [
            f"emcee: max integrated autocorrelation time {table_emcee['autocorr_time'].max():.0f} "
            f"steps; {int((table_emcee.groupby('vehicle')['autocorr_reliable'].first() == 0).sum())}"
            " vehicle(s) with a run shorter than 50 tau.",
            "",
        ]
    if args.nuts_batch:
        timings = nuts_batch_timing(jax.random.key(args.seed), arrays)
        lines += [
            "NUTS vectorisation (800 draws, 200 warm-up, 4 chains; seconds): "
            + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()),
            "",
        ]
    lines += [
        f"Agreement criterion: {CRITERION}.",
        "",
        "## Per engine pair and parameter (share of vehicles)",
        "",
        markdown(summary),
        "",
        "## Mean log-likelihood of each engine's draws (nats, summed over steps)",
        "",
        markdown(mean_log_likelihood(trees).reset_index()),
        "",
        "## Vehicles and parameters that fail the criterion",
        "",
        markdown(
            table.loc[
                ~table["agree"],
                ["a", "b", "vehicle", "param", "mean_diff_sd", "sd_ratio", "wasserstein_sd"],
            ]
        ),
        "",
        "![agreement](agreement_heatmap.png)",
        "",
    ]
    write_text_atomic(args.out / "agreement.md", "\n".join(lines))
    print(summary.to_string())
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
