"""The highway table's calibration at another rollout seed, from a main job's saved fits.

The paper's highway experiment (``bayesdrive/experiments/paper.py``, ``highway_step``) rolls
each learned model out from one fixed key. This script keeps everything else of a finished main
job (its scenarios, its smc fits of the IDM and of the criticism's final model, its settings)
and draws the rollouts from another key, so a calibration figure can be checked on seeds that
were not looked at. pf's fit is left out (its table row is not what the check is about).

    python benchmarks/highway_rollout_seed.py --results <main job folder> --seed <seed> --out <json>
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax

from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.drivers.closed_loop import forecast_start
from bayesdrive.experiments import paper
from bayesdrive.inference.core.output import load_result
from bayesdrive.simulation.metrics import evaluate_policy
from bayesdrive.simulation.scenarios import with_history

LABELS = ("ngsim_i80_chains", "openacc_vicolungo:human")
SKIPPED_FITS = ("pf",)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--results", type=Path, required=True, help="a main job's --out folder")
    parser.add_argument("--seed", type=int, required=True, help="the rollouts' seed")
    parser.add_argument("--out", type=Path, required=True, help="JSON written here")
    args = parser.parse_args()
    settings = paper.main_steps(paper.FULL)
    rows = {}
    for label in LABELS:
        traj = paper.highway_data(label.split(":")[0])[label]
        folder = paper.highway_folder(args.results, label)
        trees = {
            path.stem: load_result(path)
            for path in sorted(folder.glob("*.nc"))
            if path.stem not in SKIPPED_FITS
        }
        scenarios = paper._highway_scenarios(label, traj, settings)
        scored, _ = with_history(paper._covered(scenarios, trees), traj)
        for tree in trees.values():
            name, policy = paper._learned_policy(tree)
            start = forecast_start(policy.model)
            result = evaluate_policy(
                jax.random.key(args.seed),
                policy,
                scored,
                num_rollouts=settings.rollouts,
                start=start,
            )
            rows[f"{label} {name} ({start})"] = result["calibration_position"]
            print(label, name, start, result["calibration_position"], flush=True)
    payload = {"seed": args.seed, "rollouts": settings.rollouts, "calibration_position": rows}
    write_text_atomic(args.out, json.dumps(payload, indent=2) + "\n")


if __name__ == "__main__":
    main()
