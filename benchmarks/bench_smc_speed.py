"""smc's speed on the whole NGSIM I-80 sample: its defaults against the earlier defaults, in one
process.

The 187 chain followers' fitting windows of ``ngsim_i80_chains`` (those with usable steps), six
IDM parameters, 1000 particles, one JAX CPU device per core (what the ``bayesdrive`` command sets
up), seed 0. Both settings fit the same data in the same process, alternating ``--rounds`` times,
so their inference times compare as a ratio even on a machine that other jobs share; the
absolute seconds hold only for the load at the time. Per setting it also records where the work
goes: tempering stages, closing moves (and the likelihood evaluations each costs: a paired move
scores the cloud twice) and their spread over the vehicles. Writes ``<out>/smc_speed.md``.

The agreement of the same settings with the NUTS reference is ``benchmarks/bench_smc_moves.py``.

Run: ``PYTHONPATH=. python benchmarks/bench_smc_speed.py --note "quiet machine"``
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

# One JAX CPU device per core, as the ``bayesdrive`` command sets up, before JAX is imported.
if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "")
        + f" --xla_force_host_platform_device_count={os.cpu_count() or 1}"
    ).strip()

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bayesdrive.data.atomic import write_text_atomic  # noqa: E402
from benchmarks.bench_agreement import markdown  # noqa: E402
from benchmarks.bench_scaling import commit, machine, ngsim_followers  # noqa: E402

# The defaults before the paired closing moves: random-walk closing moves in blocks of 80, at
# most 2000.
EARLIER = {"paired_closing": False, "final_moves": 80, "max_final_moves": 2000}
SETTINGS = {"earlier defaults": EARLIER, "defaults": {}}


def fit_once(arrays, options: dict, seed: int) -> dict:
    """One fit of every vehicle; its times and where the moves went."""
    import jax

    from bayesdrive.drivers.idm import IDM
    from bayesdrive.inference.engines import smc

    result = smc.run(jax.random.key(seed), arrays, model=IDM, num_particles=1000, **options)
    stats = result.sample_stats
    stages = np.asarray(stats["temper_stages"][1]).ravel()
    closing = np.asarray(stats["final_moves"][1]).ravel()
    evaluations_per_closing_move = 2 if result.options["paired_closing"] else 1
    tempering_evaluations = stages * result.options["temper_moves"]
    closing_evaluations = closing * evaluations_per_closing_move
    return {
        "inference_s": result.wall_time_s,
        "compile_s": result.compile_time_s,
        "stages": stages,
        "closing": closing,
        "tempering_evaluations": int(tempering_evaluations.sum()),
        "closing_evaluations": int(closing_evaluations.sum()),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--note", default="", help="the machine's state, e.g. 'shared'")
    parser.add_argument("--out", type=Path, default=ROOT / "reports")
    args = parser.parse_args(argv)

    version = commit()
    arrays = ngsim_followers(0)
    runs: dict[str, list[dict]] = {label: [] for label in SETTINGS}
    for round_index in range(args.rounds):
        for label, options in SETTINGS.items():
            runs[label].append(fit_once(arrays, options, args.seed))
            print(
                f"round {round_index}, {label}: {runs[label][-1]['inference_s']:.1f} s", flush=True
            )

    rows = []
    for label, done in runs.items():
        last = done[-1]
        rows.append(
            {
                "setting": label,
                "inference (s), each round": ", ".join(f"{r['inference_s']:.1f}" for r in done),
                # Later rounds find the compiled program in the cache.
                "compilation (s), first round": done[0]["compile_s"],
                "stages (median, max)": (
                    float(np.median(last["stages"])),
                    int(last["stages"].max()),
                ),
                "closing moves (median, mean, max)": (
                    float(np.median(last["closing"])),
                    round(float(last["closing"].mean()), 1),
                    int(last["closing"].max()),
                ),
                "likelihood evaluations of the cloud, tempering / closing": (
                    f"{last['tempering_evaluations']} / {last['closing_evaluations']}"
                ),
            }
        )
    ratios = [
        earlier["inference_s"] / new["inference_s"]
        for earlier, new in zip(runs["earlier defaults"], runs["defaults"], strict=True)
    ]
    vehicles = len(arrays.vehicle_ids)
    steps = int(np.asarray(arrays.mask).sum())
    lines = [
        "# smc's speed on the whole NGSIM I-80 sample (benchmarks/bench_smc_speed.py)",
        "",
        f"Run at commit {version}, on {machine()}"
        + (f" ({args.note})" if args.note else "")
        + f"; one JAX CPU device per core. {vehicles} chain followers' fitting windows of "
        f"ngsim_i80_chains ({steps:,} steps), six IDM parameters, 1000 particles, seed "
        f"{args.seed}. Both settings in one process, alternating, {args.rounds} round(s); "
        "inference only, compilation apart.",
        "",
        f"Earlier defaults: `{EARLIER}`.",
        "",
        markdown(pd.DataFrame(rows), "{:.1f}"),
        "",
        "Speed-up of the defaults over the earlier defaults (inference time, each round): "
        + ", ".join(f"{r:.2f}x" for r in ratios)
        + ".",
        "",
        "The levers weighed before choosing the defaults, with their agreement counts: "
        "`smc_levers.md`.",
        "",
    ]
    write_text_atomic(args.out / "smc_speed.md", "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
