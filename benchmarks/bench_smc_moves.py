"""smc's moves on the agreement vehicles, judged against the saved NUTS reference: the defaults
(random-walk tempering moves, paired independent + random-walk closing moves), the paired moves
everywhere (``independent=True``) and the earlier defaults (the random walk alone, closing moves
included, in blocks of 80).

All settings fit the 15 vehicles of ``benchmarks/bench_agreement.py`` (same choice rule, fitting
windows, six IDM parameters, 1000 particles, 20 replicates, seed 7) in one process, so their wall
times compare as a ratio. Each is judged per vehicle and parameter by the agreement criterion
(:func:`bayesdrive.inference.diagnostics.agreement.judge`) against the NUTS rows (128,000 draws) of the
committed ``reports/agreement/agreement.csv``, so the long NUTS run is not repeated. Writes
``reports/agreement/smc_moves.md`` and ``smc_moves.csv``.

Run: ``PYTHONPATH=. python benchmarks/bench_smc_moves.py``
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bayesdrive.data.atomic import write_text_atomic  # noqa: E402
from bayesdrive.data.registry import load  # noqa: E402
from bayesdrive.data.views import follower_arrays  # noqa: E402
from bayesdrive.drivers.idm import IDM  # noqa: E402
from bayesdrive.inference.core.output import metadata  # noqa: E402
from bayesdrive.inference.diagnostics.agreement import (  # noqa: E402
    CRITERION,
    judge,
    mcse_mean,
    mcse_sd,
)
from bayesdrive.inference.fit import fit  # noqa: E402
from benchmarks.bench_agreement import DATA, choose_vehicles, markdown  # noqa: E402
from benchmarks.bench_scaling import commit  # noqa: E402

# The paired moves with the move counts they were measured at (10 a stage: fewer left a bias).
PAIRED = {
    "independent": True,
    "num_moves": 3,
    "temper_moves": 10,
    "final_moves": 5,
    "max_final_moves": 1000,
}
# The defaults before the paired closing moves (benchmarks/bench_smc_speed.py times both).
RANDOM_WALK = {"paired_closing": False, "final_moves": 80, "max_final_moves": 2000}
SETTINGS = {"defaults": {}, "paired": PAIRED, "random walk": RANDOM_WALK}


def judged(tree, reference: pd.DataFrame, label: str) -> pd.DataFrame:
    """One row per vehicle and parameter: this run against the reference's NUTS columns."""
    posterior = tree["posterior"].to_dataset()
    errors, sd_errors = mcse_mean(tree), mcse_sd(tree)
    rows = []
    for ref in reference.itertuples(index=False):
        draws = posterior[ref.param].sel(vehicle=str(ref.vehicle)).values.ravel()
        mcse = float(errors[ref.param].sel(vehicle=str(ref.vehicle)))
        sd_mcse = float(sd_errors[ref.param].sel(vehicle=str(ref.vehicle)))
        # NUTS rows saved before the sd criterion counted Monte Carlo error carry no sd error:
        # it counts as 0 there (the stricter side).
        verdict = judge(
            draws.mean(),
            draws.std(),
            mcse,
            ref.mean_b,
            ref.sd_b,
            ref.mcse_b,
            mcse_sd_a=sd_mcse,
            mcse_sd_b=getattr(ref, "mcse_sd_b", 0.0),
        )
        rows.append(
            {
                "setting": label,
                "vehicle": str(ref.vehicle),
                "param": ref.param,
                "mean": draws.mean(),
                "nuts_mean": ref.mean_b,
                "sd": draws.std(),
                "nuts_sd": ref.sd_b,
                "mean_diff_sd": (draws.mean() - ref.mean_b) / verdict.pooled_sd,
                "sd_ratio": draws.std() / ref.sd_b,
                "agree": verdict.agree_mean and verdict.agree_sd,
            }
        )
    return pd.DataFrame(rows)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", type=int, default=15)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--replicates", type=int, default=20)
    parser.add_argument("--out", type=Path, default=ROOT / "reports" / "agreement")
    args = parser.parse_args(argv)

    version = commit()
    saved = pd.read_csv(args.out / "agreement.csv")
    reference = saved[(saved["a"] == "smc") & (saved["b"] == "nuts")]
    traj = load(DATA)
    vehicles = choose_vehicles(traj, args.vehicles)
    arrays = follower_arrays(traj, window="fit", vehicle_ids=vehicles)
    reference = reference[reference["vehicle"].astype(str).isin(vehicles)]

    tables, times, compile_times, stats = [], {}, {}, {}
    for label, options in SETTINGS.items():
        tree = fit(
            jax.random.key(args.seed),
            arrays,
            model=IDM,
            engine="smc",
            seed=args.seed,
            num_particles=1000,
            replicates=args.replicates,
            **options,
        )
        recorded = metadata(tree)
        times[label] = recorded["wall_time_s"]
        compile_times[label] = recorded["compile_time_s"]
        sample_stats = tree["sample_stats"]
        stats[label] = {
            "final moves (median, max)": (
                float(np.median(sample_stats["final_moves"].values)),
                int(sample_stats["final_moves"].values.max()),
            ),
            "final acceptance (median)": float(np.median(sample_stats["final_acceptance"].values)),
        }
        tables.append(judged(tree, reference, label))
        print(f"{label}: {times[label]:.0f} s", flush=True)

    table = pd.concat(tables, ignore_index=True)
    write_text_atomic(args.out / "smc_moves.csv", table.to_csv(index=False))
    summary = (
        table.groupby("setting")["agree"]
        .agg(["sum", "count"])
        .reindex(list(SETTINGS))
        .reset_index()
    )
    summary.columns = ["setting", "agree", "of"]
    summary["inference (s)"] = [times[s] for s in summary["setting"]]
    summary["compilation (s)"] = [compile_times[s] for s in summary["setting"]]
    summary["closing moves (median, max)"] = [
        stats[s]["final moves (median, max)"] for s in summary["setting"]
    ]
    failing = table.loc[
        ~table["agree"], ["setting", "vehicle", "param", "mean_diff_sd", "sd_ratio"]
    ]
    lines = [
        "# smc's moves against the saved NUTS reference (benchmarks/bench_smc_moves.py)",
        "",
        f"Run at commit {version}.",
        "",
        f"{len(vehicles)} vehicles ({', '.join(vehicles)}), fitting windows of {DATA}, six IDM "
        f"parameters, 1000 particles, {args.replicates} replicates, seed {args.seed}; all "
        "settings in one process. Reference: the NUTS rows (128,000 draws) of `agreement.csv`.",
        "",
        f"Settings: defaults = smc's defaults (paired closing moves); paired = "
        f"`{json.dumps(PAIRED)}`; random walk = `{json.dumps(RANDOM_WALK)}` (the earlier "
        "defaults).",
        "",
        f"Agreement criterion: {CRITERION}.",
        "",
        markdown(summary, "{:.1f}"),
        "",
        "Speed-up over the random walk (inference): "
        + ", ".join(
            f"{label} {times['random walk'] / times[label]:.2f}x"
            for label in SETTINGS
            if label != "random walk"
        )
        + ".",
        "",
        "## Vehicles and parameters that fail the criterion",
        "",
        markdown(failing),
        "",
    ]
    write_text_atomic(args.out / "smc_moves.md", "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
