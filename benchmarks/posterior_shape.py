"""The shape of one vehicle's posterior, as engines saw it: where a sampler may mix slowly.

For each result file (one per engine), one vehicle's draws: per parameter the mean and sd, the
lowest and highest draw against the prior box, and the skewness and excess kurtosis on the box's
logit scale (a thin tail pressed against a bound shows as a large skew there); the correlation
matrix; and, for a named pair, whether the ridge between them is straight (the residual sd of
the second on the first, fitted by a line and by a parabola). Prints a Markdown report.

    PYTHONPATH=. python benchmarks/posterior_shape.py --vehicle 140 --pair d_min,tau \
        emcee=runs/emcee.nc smc=runs/smc.nc
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np
from scipy import stats

from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.core.output import load_result, metadata
from bayesdrive.inference.population.two_stage import _logit_box_draws


def vehicle_draws(path: str, vehicle: str) -> tuple[list[str], np.ndarray, np.ndarray, Any]:
    """The parameter names, ``vehicle``'s (draws, parameters) array in natural units and on the
    prior box's logit scale, and the fitted model."""
    tree = load_result(path)
    posterior = tree["posterior"]
    names = list(posterior.data_vars)
    ids = [str(v) for v in posterior["vehicle"].values]
    if vehicle not in ids:
        raise SystemExit(f"{path}: no vehicle {vehicle!r} (it has {', '.join(ids)})")
    at = ids.index(vehicle)
    model = get_model(metadata(tree)["model"])
    draws = np.stack([posterior[n].isel(vehicle=at).values.reshape(-1) for n in names], axis=1)
    return names, draws, _logit_box_draws(tree, model.prior(names), names)[at], model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", nargs="+", help="LABEL=PATH of a saved result")
    parser.add_argument("--vehicle", required=True)
    parser.add_argument("--pair", default=None, help="A,B: is the ridge of B on A straight?")
    args = parser.parse_args()
    print(f"Vehicle {args.vehicle}.\n")
    rows, correlations, ridges = [], [], []
    for labelled in args.results:
        label, path = labelled.split("=", 1)
        names, draws, logit, model = vehicle_draws(path, args.vehicle)
        for k, name in enumerate(names):
            spec = model.spec(name)
            rows.append(
                f"| {name} | {label} | {draws[:, k].mean():.4g} | {draws[:, k].std():.3g} "
                f"| [{spec.lower:g}, {spec.upper:g}] | {draws[:, k].min():.4g} "
                f"| {draws[:, k].max():.4g} | {stats.skew(logit[:, k]):.2f} "
                f"| {stats.kurtosis(logit[:, k]):.2f} |"
            )
        matrix = np.corrcoef(draws.T)
        correlations.append(f"{label} ({draws.shape[0]} draws):\n")
        correlations.append("| | " + " | ".join(names) + " |")
        correlations.append("|---" * (len(names) + 1) + "|")
        correlations += [
            f"| {a} | " + " | ".join(f"{c:.2f}" for c in matrix[i]) + " |"
            for i, a in enumerate(names)
        ]
        correlations.append("")
        if args.pair:
            first, second = args.pair.split(",")
            x, y = draws[:, names.index(first)], draws[:, names.index(second)]
            residual = {
                degree: np.std(y - np.polyval(np.polyfit(x, y, degree), x)) for degree in (1, 2)
            }
            ridges.append(
                f"| {label} | {np.corrcoef(x, y)[0, 1]:.2f} | {y.std():.4g} | "
                f"{residual[1]:.4g} | {residual[2]:.4g} |"
            )
    print(
        "| parameter | engine | mean | sd | prior box | lowest | highest | skew (logit) "
        "| excess kurtosis (logit) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows) + "\n")
    print("\n".join(correlations))
    if ridges:
        first, second = args.pair.split(",")
        print(
            f"| engine | corr({first}, {second}) | sd of {second} | residual sd, line "
            "| residual sd, parabola |"
        )
        print("|---|---|---|---|---|")
        print("\n".join(ridges))


if __name__ == "__main__":
    main()
