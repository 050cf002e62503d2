"""Coverage of 90% posterior intervals on simulated IDM followers, per engine (smc, pf, nuts).

For each seed (``--seeds`` of them from ``--first-seed``; defaults 100 seeds from 0): four
followers whose (v_des, tau, sigma) are drawn from the uniform prior box, simulated for 10 s behind
a replayed synthetic leader (:func:`bayesdrive.inference.diagnostics.sbc.simulate_replications`), then fitted
by every engine of ``--engines`` (default ``smc,pf``) from the same data, each with its own key
folded from the seed (so one engine's fit of a seed is the same whichever others run). With truths
drawn from the prior, exact posteriors give central 90% intervals that cover the truth 90% of the
time, averaged over the prior; smc and nuts must show that, pf is measured (its dithering widens
and shifts its particle set, so nothing is promised). ``--particles`` (default: each engine's own
default, 1000 for smc and pf, 2000 draws for nuts) sets ``num_particles``.

Writes ``reports/coverage.md`` (or ``--out``): per engine and parameter, the coverage with a 95%
Wilson interval for it, the share of truths below and above the interval (0.05 each when exact),
the mean interval width and mean absolute error of the posterior mean in prior widths, and the run
times. ``--raw FILE.npz`` also keeps every replication's truth and interval (written every 25
seeds, so a stopped run leaves what it did). Run:
``python benchmarks/bench_coverage.py [--seeds 100] [--first-seed 0] [--engines smc,pf]``;
``--sd-doubled`` fits a likelihood with twice the execution-noise sd, a negative control whose
sigma intervals must miss.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax
import numpy as np
from scipy.stats import norm

from bayesdrive.data.atomic import write_atomic, write_text_atomic
from bayesdrive.drivers.idm import IDM
from bayesdrive.inference.diagnostics.sbc import sd_doubled, simulate_replications
from bayesdrive.inference.engines import nuts, pf, smc

PARAMS = ("v_des", "tau", "sigma")
LEVEL = 0.90
# Each engine's key is folded from the seed's fitting key by this fixed number, not by its place
# in --engines, so its fits do not change with the other engines chosen.
ENGINES = {"smc": (smc.run, 0), "pf": (pf.run, 1), "nuts": (nuts.run, 2)}
CHECKPOINT_SEEDS = 25


def wilson(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion."""
    z = norm.ppf(0.5 + confidence / 2)
    p = successes / trials
    centre = (p + z**2 / (2 * trials)) / (1 + z**2 / trials)
    half = z * np.sqrt(p * (1 - p) / trials + z**2 / (4 * trials**2)) / (1 + z**2 / trials)
    return centre - half, centre + half


def intervals(posterior: dict[str, np.ndarray]) -> np.ndarray:
    """(vehicle, param, [low, mean, high]) from posterior arrays (chain, draw, vehicle)."""
    tail = (1 - LEVEL) / 2
    out = []
    for name in PARAMS:
        draws = posterior[name].reshape(-1, posterior[name].shape[-1])
        low, high = np.quantile(draws, [tail, 1 - tail], axis=0)
        out.append(np.stack([low, draws.mean(axis=0), high], axis=-1))
    return np.stack(out, axis=1)


def coverage_table(truth: np.ndarray, found: dict[str, np.ndarray], width: np.ndarray) -> list[str]:
    """Markdown rows: per engine and parameter, coverage, its Wilson interval, one-sided misses."""
    lines = [
        "| engine | parameter | coverage of 90% intervals | 95% interval | truth below / above "
        "| mean width / prior width | mean abs error of the mean / prior width |",
        "|---|---|---|---|---|---|---|",
    ]
    trials = len(truth)
    for name, bounds in found.items():
        for k, param in enumerate(PARAMS):
            low, mean, high = bounds[:, k, 0], bounds[:, k, 1], bounds[:, k, 2]
            below = int(np.sum(truth[:, k] < low))
            above = int(np.sum(truth[:, k] > high))
            covered = trials - below - above
            lo, hi = wilson(covered, trials)
            lines.append(
                f"| {name} | {param} | {covered / trials:.3f} ({covered}/{trials}) | "
                f"{lo:.3f} - {hi:.3f} | {below / trials:.3f} / {above / trials:.3f} | "
                f"{np.mean(high - low) / width[k]:.3f} | "
                f"{np.mean(np.abs(mean - truth[:, k])) / width[k]:.3f} |"
            )
    return lines


def save_raw(
    path: Path, seeds: list[int], truths: list, found: dict[str, list], seconds: dict[str, float]
) -> None:
    """Every replication's seed, truth and (low, mean, high) per engine, and the engines'
    inference seconds so far, atomically."""
    arrays = {
        "seed": np.repeat(seeds, len(truths[0])),
        "truth": np.concatenate(truths),
        **{f"bounds_{name}": np.concatenate(rows) for name, rows in found.items()},
        **{f"seconds_{name}": np.asarray(s) for name, s in seconds.items()},
    }
    write_atomic(path, lambda tmp: np.savez(tmp, params=np.asarray(PARAMS), **arrays))


def load_raw(path: Path, seeds: list[int], engines: list[str], vehicles: int):
    """The seeds already done in ``path`` (a prefix of ``seeds``), their truths and intervals per
    seed, and the inference seconds (NaN where a file predates recording them)."""
    with np.load(path) as raw:
        done = [int(s) for s in raw["seed"][::vehicles]]
        if done != seeds[: len(done)] or tuple(raw["params"]) != PARAMS:
            raise SystemExit(f"{path}: its seeds/parameters are not a start of this run's")
        missing = [name for name in engines if f"bounds_{name}" not in raw]
        if missing:
            raise SystemExit(f"{path}: holds no intervals of engine(s) {missing}")
        truths = list(np.split(raw["truth"], len(done)))
        found = {name: list(np.split(raw[f"bounds_{name}"], len(done))) for name in engines}
        seconds = {
            name: float(raw[f"seconds_{name}"]) if f"seconds_{name}" in raw else float("nan")
            for name in engines
        }
    return done, truths, found, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=100, help="number of seeds (default 100)")
    parser.add_argument("--first-seed", type=int, default=0, help="first seed (default 0)")
    parser.add_argument("--vehicles", type=int, default=4, help="followers per seed (default 4)")
    parser.add_argument("--steps", type=int, default=100, help="steps of 0.1 s (default 100)")
    parser.add_argument(
        "--particles",
        type=int,
        default=None,
        help="num_particles of every engine (default: each engine's own default)",
    )
    parser.add_argument(
        "--engines", default="smc,pf", help=f"comma-separated, of {', '.join(ENGINES)}"
    )
    parser.add_argument(
        "--sd-doubled",
        action="store_true",
        help="negative control: fit a likelihood with twice the execution-noise sd (must miss)",
    )
    parser.add_argument("--out", type=Path, default=Path("reports/coverage.md"))
    parser.add_argument("--raw", type=Path, default=None, help="also keep replications (.npz)")
    parser.add_argument(
        "--resume", action="store_true", help="skip the seeds already in --raw, keep their results"
    )
    parser.add_argument(
        "--minutes",
        type=float,
        default=None,
        help="stop after the seed running when this many minutes have passed; report those done",
    )
    args = parser.parse_args()
    chosen = args.engines.split(",")
    unknown = sorted(set(chosen) - set(ENGINES))
    if unknown:
        parser.error(f"--engines: unknown engine(s) {unknown}; choose from {sorted(ENGINES)}")
    if args.resume and args.raw is None:
        parser.error("--resume needs --raw, the file to resume from")
    load_before = os.getloadavg()
    started = time.perf_counter()
    box = IDM.prior(PARAMS)
    width = np.asarray(box.upper - box.lower, dtype=np.float64)
    fit_model = sd_doubled(IDM) if args.sd_doubled else IDM
    options = {} if args.particles is None else {"num_particles": args.particles}
    found = {name: [] for name in chosen}
    truths = []
    seconds = dict.fromkeys(chosen, 0.0)
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    done_seeds = []
    if args.resume and args.raw.exists():
        done_seeds, truths, found, seconds = load_raw(args.raw, seeds, chosen, args.vehicles)
        print(f"resuming after {len(done_seeds)} seeds from {args.raw}", flush=True)
    for done, seed in enumerate(seeds[len(done_seeds) :], start=len(done_seeds) + 1):
        if args.minutes is not None and time.perf_counter() - started > 60 * args.minutes:
            break
        key_sim, key_fit = jax.random.split(jax.random.key(seed))
        truth, arrays = simulate_replications(
            key_sim, IDM, PARAMS, num_replications=args.vehicles, num_steps=args.steps
        )
        truths.append(truth)
        for name in chosen:
            run, engine_id = ENGINES[name]
            key = jax.random.fold_in(key_fit, engine_id)
            result = run(key, arrays, model=fit_model, params=PARAMS, **options)
            seconds[name] += result.wall_time_s
            found[name].append(intervals(result.posterior))
        done_seeds.append(seed)
        print(f"seed {seed} done ({done}/{args.seeds})", flush=True)
        if args.raw is not None and (done % CHECKPOINT_SEEDS == 0 or done == args.seeds):
            save_raw(args.raw, done_seeds, truths, found, seconds)
    if args.raw is not None:
        save_raw(args.raw, done_seeds, truths, found, seconds)

    if not done_seeds:
        raise SystemExit("no seed was fitted within --minutes; nothing to report")
    truth = np.concatenate(truths)  # (replication, param)
    lines = coverage_table(truth, {name: np.concatenate(found[name]) for name in chosen}, width)
    particles = (
        "each engine's default particle count"
        if args.particles is None
        else f"{args.particles} particles per vehicle"
    )
    text = "\n".join(
        [
            "# Coverage of posterior intervals on simulated IDM followers",
            "",
            "Generated by `benchmarks/bench_coverage.py`: "
            f"{len(done_seeds)} seeds x {args.vehicles} followers = {len(truth)} replications, "
            f"{args.steps} steps of 0.1 s each, "
            f"{particles}, engines {', '.join(chosen)} fitting model `{fit_model.name}`, "
            f"parameters {', '.join(PARAMS)} drawn from "
            "the uniform prior box (other IDM parameters at their defaults), seeds "
            f"{done_seeds[0]} to {done_seeds[-1]}"
            + (f" (of {seeds[0]} to {seeds[-1]} planned)" if len(done_seeds) < len(seeds) else "")
            + f". Load average at the start: {load_before[0]:.1f}; run time of this invocation "
            f"{(time.perf_counter() - started) / 60:.1f} min.",
            "",
            *lines,
            "",
            "Exact posteriors cover at the nominal 90% when truths are drawn from the prior; a "
            "95% interval excluding 0.90 is evidence of miscalibration. pf (the paper's filter, "
            "1 epoch, grid steps "
            f"{', '.join(f'{p} {IDM.spec(p).grid_step}' for p in PARAMS)}) is measured, not "
            "required to be calibrated: dithering is an artificial random walk on the parameters.",
            "",
            "Inference time (compilation excluded): "
            + ", ".join(
                f"{name} " + ("not recorded" if np.isnan(s) else f"{s:.1f} s")
                for name, s in seconds.items()
            )
            + ".",
            "",
        ]
    )
    write_text_atomic(args.out, text)
    print(text)


if __name__ == "__main__":
    main()
