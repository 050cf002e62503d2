"""Closed-loop baselines on every data set the simulator can score, and the simulator's speed.

Writes to ``--out`` (default ``reports/simulation``):

* ``baselines.json``: every metric of every (data set, baseline) run, with the scenario sets and
  the platoon sizes each data set allows;
* ``baselines.md``: the headline table;
* ``rollout_speed.json``: compile time and steady-state time of ``rollout`` (IDM) per shape.

Data sets for fitting are scored with every applicable baseline. Held-out data sets are scored
only with baselines that fit nothing on them (``idm-default``, ``idm-nls``, ``cv``, ``ca``):
they exist to measure generalisation, never to fit or tune. Platoon size: 4 simulated vehicles
(an OpenACC platoon behind its leader), or the largest size the data allow if smaller.

Run: ``python benchmarks/simulation_baselines.py [--out DIR] [--rollouts 100] [--seed 0]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

from bayesdrive.data import registry
from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.drivers.idm import IDM
from bayesdrive.simulation.baselines import baseline_policy
from bayesdrive.simulation.metrics import evaluate_policy
from bayesdrive.simulation.rollout import broadcast_params, platoon_scene, rollout
from bayesdrive.simulation.scenarios import merge_scenarios, platoon_scenarios, scenario_capacity

FIT_SETS = ("ngsim_i80_chains", "openacc_vicolungo", "ngsim_merge_episodes")
HELDOUT_SETS = ("openacc_zalazone", "openacc_casale", "acc_platoon_fhwa", "ngsim_i80_pairs_b")
PLATOON_BASELINES = ("idm-default", "idm-nls", "idm-lm", "cv", "ca", "blackbox")
MERGE_BASELINES = ("cidm-c1", "idm-nomerge", "idm-default", "idm-nls", "cv", "ca")
FITS_NOTHING = ("idm-default", "idm-nls", "cv", "ca")
VEHICLES_PER_SCENARIO = 4
HORIZON_S = 5.0


def scenario_set(traj, capacity: list[dict]):
    if traj.format == "merge_episodes":
        return merge_scenarios(traj, horizon_s=HORIZON_S)
    sizes = [row["vehicles_per_scenario"] for row in capacity]
    if not sizes:
        return None
    size = min(VEHICLES_PER_SCENARIO, max(sizes))
    return platoon_scenarios(traj, vehicles_per_scenario=size, horizon_s=HORIZON_S)


def run_data_set(name: str, held_out: bool, key, rollouts: int) -> dict:
    load = registry.load_holdout if held_out else registry.load
    traj = load(name)
    merge = traj.format == "merge_episodes"
    capacity = [] if merge else scenario_capacity(traj, horizon_s=HORIZON_S)
    scenarios = scenario_set(traj, capacity)
    entry = {"data_set": name, "held_out": held_out, "capacity": capacity, "runs": []}
    if scenarios is None or not scenarios.scenarios:
        entry["skipped"] = "no scenario of the horizon in the held-out windows"
        return entry
    entry["scenario_set"] = scenarios.summary()
    names = MERGE_BASELINES if merge else PLATOON_BASELINES
    if held_out:
        names = tuple(n for n in names if n in FITS_NOTHING)
    for baseline, baseline_key in zip(names, jax.random.split(key, len(names)), strict=True):
        key_policy, key_rollouts = jax.random.split(baseline_key)
        started = time.perf_counter()
        policy = baseline_policy(baseline, key_policy, traj, scenarios.simulated_ids)
        fitted = time.perf_counter()
        summary = evaluate_policy(key_rollouts, policy, scenarios, num_rollouts=rollouts)
        done = time.perf_counter()
        summary.pop("by_scenario")
        entry["runs"].append(
            {
                "model": baseline,
                "policy": policy.description,
                "policy_details": policy.details,
                "fit_s": fitted - started,
                "evaluate_s": done - fitted,
                **summary,
            }
        )
        print(f"{name:24s} {baseline:12s} done in {done - started:6.1f} s", file=sys.stderr)
    return entry


def rollout_speed(key, shapes: list[tuple[int, int, int]], repeats: int = 5) -> list[dict]:
    """First-call (compilation included) and steady-state time of an IDM rollout per (rollouts,
    vehicles, steps); the machine is shared, so these are upper bounds."""
    rows = []
    for num_rollouts, vehicles, steps in shapes:
        head_v = np.full(steps + 1, 15.0)
        scene = platoon_scene(
            head_v, -25.0 * np.arange(1, vehicles + 1), np.full(vehicles, 15.0), length=4.5, dt=0.1
        )
        params = broadcast_params(IDM.defaults(), num_rollouts, vehicles)
        jax.clear_caches()  # the first call then always includes compilation
        started = time.perf_counter()
        jax.block_until_ready(rollout(key, IDM, params, scene, num_rollouts=num_rollouts))
        first = time.perf_counter() - started
        times = []
        for _ in range(repeats):
            started = time.perf_counter()
            jax.block_until_ready(rollout(key, IDM, params, scene, num_rollouts=num_rollouts))
            times.append(time.perf_counter() - started)
        steady = float(np.median(times))
        rows.append(
            {
                "rollouts": num_rollouts,
                "vehicles": vehicles,
                "steps": steps,
                "first_call_s": first,
                "median_s": steady,
                "vehicle_steps_per_s": num_rollouts * vehicles * steps / steady,
            }
        )
        print(f"rollout {num_rollouts}x{vehicles}x{steps}: {steady * 1e3:.2f} ms", file=sys.stderr)
    return rows


def _mean_sd(summary: dict) -> str:
    sd = summary["sd"]
    return f"{summary['mean']:.2f}" + (f" ± {sd:.2f}" if sd is not None else "")


def markdown(results: list[dict], speed: list[dict], rollouts: int, seed: int) -> str:
    lines = [
        "# Closed-loop baselines",
        "",
        f"Generated by `benchmarks/simulation_baselines.py` (seed {seed}, {rollouts} rollouts "
        f"per scenario, horizon {HORIZON_S} s). RMSE: root mean square over vehicles and "
        "rollouts at the horizon, mean ± sd over scenarios; MAE (paper): mean absolute position "
        "error at the last step, as the paper's code reported. Collisions: events over all "
        "rollouts and the share of vehicle-rollouts that collide. Hard braking: steps at or "
        "below -3 m/s^2 per rollout (all scenarios), beside the data's count. W1: Wasserstein "
        "distance of the simulated speed / gap distribution to the data's.",
        "",
        "| data set | scenes x N | model | RMSE x (m) | RMSE v (m/s) | MAE x (paper) | "
        "collisions | hard braking / data | W1 speed | W1 gap |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for entry in results:
        label = entry["data_set"] + (" (held out)" if entry["held_out"] else "")
        if "skipped" in entry:
            lines.append(f"| {label} | - | - | {entry['skipped']} | | | | | | |")
            continue
        scenes = entry["scenario_set"]
        size = f"{scenes['scenarios']} x {scenes['vehicles_per_scenario']}"
        for run in entry["runs"]:
            lines.append(
                f"| {label} | {size} | {run['model']} | {_mean_sd(run['rmse_position_m'])} | "
                f"{_mean_sd(run['rmse_speed_mps'])} | "
                f"{_mean_sd(run['paper_mae_last_step']['position_m'])} | "
                f"{run['collisions']['total']} ({run['collisions']['fraction']:.1%}) | "
                f"{run['hard_braking']['per_rollout']:.1f} / {run['hard_braking']['data_total']} | "
                f"{run['speed_distribution_mps']['wasserstein']:.2f} | "
                f"{run['gap_distribution_m']['wasserstein']:.2f} |"
            )
    lines += ["", "## Platoon sizes the data allow (5 s windows in held-out windows)", ""]
    for entry in results:
        sizes = ", ".join(
            f"{row['vehicles_per_scenario']}: {row['scenarios']}" for row in entry["capacity"]
        )
        if sizes:
            lines.append(f"- {entry['data_set']}: {sizes} (simulated vehicles: scenarios)")
    lines += ["", "## Rollout speed (IDM; the machine is shared, so upper bounds)", ""]
    lines.append(
        "| rollouts x vehicles x steps | first call incl. compilation (s) | median call (ms) | vehicle-steps/s |"
    )
    lines.append("|---|---|---|---|")
    for row in speed:
        lines.append(
            f"| {row['rollouts']} x {row['vehicles']} x {row['steps']} | "
            f"{row['first_call_s']:.2f} | {row['median_s'] * 1e3:.2f} | "
            f"{row['vehicle_steps_per_s']:.3g} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("reports/simulation"))
    parser.add_argument("--rollouts", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="fit data sets only, small speed run")
    args = parser.parse_args(argv)

    key_data, key_speed = jax.random.split(jax.random.key(args.seed))
    sets = [(n, False) for n in FIT_SETS] + (
        [] if args.quick else [(n, True) for n in HELDOUT_SETS]
    )
    results = [
        run_data_set(name, held_out, key, args.rollouts)
        for (name, held_out), key in zip(sets, jax.random.split(key_data, len(sets)), strict=True)
    ]
    shapes = (
        [(100, 4, 50)] if args.quick else [(10, 4, 50), (100, 4, 50), (1000, 4, 50), (100, 20, 50)]
    )
    speed = rollout_speed(key_speed, shapes)
    record = {
        "seed": args.seed,
        "rollouts": args.rollouts,
        "horizon_s": HORIZON_S,
        "jax_backend": jax.default_backend(),
        "results": results,
    }
    write_text_atomic(args.out / "baselines.json", json.dumps(record, indent=2) + "\n")
    write_text_atomic(args.out / "rollout_speed.json", json.dumps(speed, indent=2) + "\n")
    write_text_atomic(args.out / "baselines.md", markdown(results, speed, args.rollouts, args.seed))


if __name__ == "__main__":
    main()
