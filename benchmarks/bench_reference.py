"""Long-run references for the vehicles where engines disagree in ``bench_agreement``.

For each ``--vehicles`` id of ``ngsim_i80_chains`` (fitting window, all six IDM parameters, the
uniform prior box, as in ``bench_agreement``): ``nuts`` with 8 chains x 50 000 draws (12 times the
agreement run) as the reference, and ``smc`` at the agreement settings (20 replicates x 1000
particles). A disagreement in the agreement table is the short-run engine's error where its own
numbers sit far from the reference and the other's sit close to it.

Writes ``reports/agreement/reference.md`` (or ``--out``). Run:
``python benchmarks/bench_reference.py --vehicles 124,140``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import numpy as np

from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.data.registry import load
from bayesdrive.data.views import follower_arrays
from bayesdrive.drivers.idm import IDM
from bayesdrive.inference.fit import fit

DATA = "ngsim_i80_chains"
ENGINE_OPTIONS = {
    "nuts (reference)": ("nuts", {"num_particles": 400_000, "num_chains": 8, "num_warmup": 3000}),
    "smc": ("smc", {"num_particles": 1000, "replicates": 20}),
}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", default="124,140")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--out", type=Path, default=Path("reports/agreement"))
    args = parser.parse_args(argv)

    traj = load(DATA, data_dir=args.data_dir)
    lines = [
        "# Long-run references (benchmarks/bench_reference.py)",
        "",
        f"{DATA}, fitting windows, all six IDM parameters, uniform prior box, seed {args.seed}. "
        "Engine settings: "
        + "; ".join(f"{label}: {engine} {opts}" for label, (engine, opts) in ENGINE_OPTIONS.items())
        + ". Mean and sd of each parameter's draws; se is the Monte Carlo standard error from the "
        "spread of chain (nuts) or replicate (smc) means.",
        "",
        "| vehicle | engine | param | mean | sd | se | run time (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for vehicle in args.vehicles.split(","):
        arrays = follower_arrays(traj, window="fit", vehicle_ids=[vehicle])
        for label, (engine, options) in ENGINE_OPTIONS.items():
            started = time.perf_counter()
            tree = fit(
                jax.random.key(args.seed),
                arrays,
                model=IDM,
                engine=engine,
                seed=args.seed,
                **options,
            )
            seconds = time.perf_counter() - started
            for name in IDM.param_names:
                draws = tree["posterior"][name].values.reshape(tree["posterior"][name].shape[0], -1)
                chain_means = draws.mean(axis=1)
                se = chain_means.std(ddof=1) / np.sqrt(len(chain_means))
                lines.append(
                    f"| {vehicle} | {label} | {name} | {draws.mean():.4g} | {draws.std():.4g} | "
                    f"{se:.2g} | {seconds:.0f} |"
                )
            print(f"{vehicle} {label}: {seconds:.0f} s", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out / "reference.md", "\n".join(lines) + "\n")
    print(f"written to {args.out / 'reference.md'}")


if __name__ == "__main__":
    main()
