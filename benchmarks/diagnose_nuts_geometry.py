"""Why is nuts slow on a model? A short nuts fit of the IDM and of the model that
``bench_crosscheck_convergence.py`` fits to ``--data``, on the same trafficgen followers (that
study's data for ``--data``), each from its own key, with the adapted step sizes and tree depths;
and the cost of one log-likelihood gradient of each, on one vehicle's series. Prints a markdown
report.

    python benchmarks/diagnose_nuts_geometry.py --data drifting_parameters --seed 20261207
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import pandas as pd  # noqa: E402

from bayesdrive.data.readers import read  # noqa: E402
from bayesdrive.data.views import follower_arrays  # noqa: E402
from bayesdrive.drivers.registry import get_model  # noqa: E402
from bayesdrive.inference.core.likelihood import (  # noqa: E402
    fixed_params,
    series_loglik,
    step_inputs,
)
from bayesdrive.inference.fit import fit  # noqa: E402
from benchmarks.bench_crosscheck_convergence import DATA, generate_data, markdown  # noqa: E402

REPEATS = 50


def nuts_row(key, data, model, followers: int, draws: int, seed: int, init_candidates: int) -> dict:
    started = time.perf_counter()
    tree = fit(
        key,
        data,
        model=model,
        engine="nuts",
        seed=seed,
        max_vehicles=followers,
        draws=draws,
        warmup=draws,
        chains=2,
        max_extension=1,
        init_candidates=init_candidates,
    )
    stats = tree["sample_stats"].to_dataset()
    return {
        "model": model.name,
        "wall_s": round(time.perf_counter() - started, 1),
        "tree_depth_mean": round(float(stats["tree_depth"].mean()), 2),
        "tree_depth_max": int(stats["tree_depth"].max()),
        "leapfrog_steps_mean": round(float(stats["n_steps"].mean()), 1),
        # One line, so the markdown row holds (a 2-d array prints a line per vehicle).
        "step_size (vehicle x chain)": str(
            [[float(f"{x:.3g}") for x in row] for row in stats["step_size"].values]
        ),
        "divergences": int(stats["diverging"].sum()),
    }


def gradient_row(model, arrays, vehicle: int) -> dict:
    """Milliseconds per log-likelihood and per value-and-gradient on one vehicle's series, at the
    model's defaults."""
    series = jax.tree.map(lambda a: a[vehicle], step_inputs(arrays, model))
    names, fixed = model.param_names, fixed_params(model, None)
    theta = jnp.asarray([s.default for s in model.specs], float)

    def total(th):
        return jnp.sum(series_loglik(model, names, fixed, th, series))

    times = {}
    for label, function in (
        ("value", jax.jit(total)),
        ("value_and_grad", jax.jit(jax.value_and_grad(total))),
    ):
        jax.block_until_ready(function(theta))
        started = time.perf_counter()
        for _ in range(REPEATS):
            jax.block_until_ready(function(theta))
        times[f"{label}_ms"] = round((time.perf_counter() - started) / REPEATS * 1e3, 3)
    return {"model": model.name, "steps": int(series.mask.sum()), **times}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="drifting_parameters", choices=sorted(DATA))
    parser.add_argument("--followers", type=int, default=2)
    parser.add_argument("--draws", type=int, default=200, help="draws and warm-up per chain")
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument(
        "--init-candidates", type=int, default=1, help="uniform start draws per chain, best kept"
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        path = generate_data(args.data, args.seed, args.followers, 60.0, Path(folder))
        data = read(path, format="ngsim_raw")
        arrays = follower_arrays(data, window="fit")
        models = [get_model("idm"), get_model(DATA[args.data][1])]
        keys = jax.random.split(jax.random.key(args.seed), len(models))
        fits = [
            nuts_row(k, data, m, args.followers, args.draws, args.seed, args.init_candidates)
            for k, m in zip(keys, models, strict=True)
        ]
        gradients = [gradient_row(m, arrays, 0) for m in models]
    print(
        f"`python benchmarks/diagnose_nuts_geometry.py --data {args.data} --followers "
        f"{args.followers} --draws {args.draws} --seed {args.seed} --init-candidates "
        f"{args.init_candidates}`\n"
    )
    print("## nuts, 2 chains, no extension\n")
    print(markdown(pd.DataFrame(fits)))
    print("\n## One vehicle's log-likelihood, at the model's defaults\n")
    print(markdown(pd.DataFrame(gradients)))


if __name__ == "__main__":
    main()
