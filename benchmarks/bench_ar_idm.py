"""AR-IDM against the white-noise IDM on every NGSIM I-80 chain follower (issue 13, "Anchor").

The anchor: Zhang, Wang & Sun (2023) fitted an IDM with AR(1) execution noise to HighD followers
with PyMC NUTS; it cut the 3 s gap RMSE from 0.32-0.39 m (independent noise) to 0.12 m, and one
chain took 30,445 s. Here both ``idm`` and ``idm+autocorrelated_noise`` are fitted with ``smc`` at
its defaults on the fitting windows of every ``ngsim_i80_chains`` follower with usable steps
(``bayesdrive fit DATA --model M --engine smc``), then scored on the held-out windows with the
library's own closed-loop evaluation (what ``bayesdrive evaluate --posterior`` runs), one simulated
vehicle per scenario behind its replayed leader, so the gap error equals the position error.

Also the held-out log predictive density per vehicle, log mean over posterior draws of
p(y_held | theta), each held-out window scored on its own (the AR residual restarts from its
stationary law there: it does not carry the fitting window's last residual, which costs the AR
model a little at the window's first steps).

Resumable: each model's fit is saved to ``--out`` (``fit_<model>.nc``) and reused when present.

Writes ``--out``/``ar_idm_anchor.json`` (all numbers), ``ar_idm_per_vehicle.csv`` and
``ar_idm_per_scenario.csv``. Run: ``python benchmarks/bench_ar_idm.py [--seed 13]``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import numpy as np
import pandas as pd
from scipy import stats
from scipy.special import logsumexp

from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.data.registry import load
from bayesdrive.data.views import follower_arrays
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.fit import fit
from bayesdrive.inference.likelihood import param_names, score_draws, step_inputs
from bayesdrive.inference.output import load_result, metadata, save_result
from bayesdrive.simulation.evaluation import evaluate, evaluation_scenarios
from bayesdrive.simulation.posterior import fixed_params, particles_by_vehicle

DATA = "ngsim_i80_chains"
MODELS = ("idm", "idm+autocorrelated_noise")
HORIZON_S = 3.0


def paired_interval(differences: np.ndarray, level: float = 0.95) -> dict[str, float]:
    """Mean of paired differences with a t interval (units independent)."""
    d = np.asarray(differences, np.float64)
    d = d[np.isfinite(d)]
    half = stats.t.ppf(0.5 + level / 2, d.size - 1) * d.std(ddof=1) / np.sqrt(d.size)
    return {
        "mean": float(d.mean()),
        "low": float(d.mean() - half),
        "high": float(d.mean() + half),
        "n": int(d.size),
        "share_negative": float(np.mean(d < 0)),
    }


def fitted(key, traj, name: str, out: Path, seed: int) -> tuple[object, dict]:
    """The model's smc fit on the fitting windows (saved, or reused from a previous run)."""
    path = out / f"fit_{name}.nc"
    if path.exists():
        print(f"{name}: reusing {path}", flush=True)
        tree = load_result(path)
        meta = metadata(tree)
        return tree, {
            "compile_time_s": meta["compile_time_s"],
            "wall_time_s": meta["wall_time_s"],
            "reused": True,
        }
    started = time.perf_counter()
    last = [started]

    def progress(done: int, total: int) -> None:
        now = time.perf_counter()
        print(
            f"{name}: {done}/{total} vehicles, {now - started:.0f} s (+{now - last[0]:.0f} s)",
            flush=True,
        )
        last[0] = now

    tree = fit(
        key,
        traj,
        model=get_model(name),
        engine="smc",
        window="fit",
        seed=seed,
        progress=progress,
        source=DATA,
    )
    total = time.perf_counter() - started
    save_result(tree, path)
    meta = metadata(tree)
    return tree, {
        "compile_time_s": meta["compile_time_s"],
        "wall_time_s": meta["wall_time_s"],
        "total_s": total,
        "reused": False,
    }


def heldout_lpd(tree, name: str, traj) -> pd.Series:
    """Per vehicle: log mean over the posterior draws of p(y_held | theta)."""
    model = get_model(name)
    meta = metadata(tree)
    names = param_names(model, meta.get("params"))
    draws = particles_by_vehicle(tree, names)
    arrays = follower_arrays(traj, window="heldout", vehicle_ids=sorted(draws))
    ids = list(arrays.vehicle_ids)
    particles = np.stack([draws[v] for v in ids])
    per_step = score_draws(
        model, names, fixed_params(model, meta), particles, step_inputs(arrays, model)
    )
    summed = per_step.sum(axis=-1)
    return pd.Series(logsumexp(summed, axis=1) - np.log(summed.shape[1]), index=ids)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=13)
    parser.add_argument("--rollouts", type=int, default=100)
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--out", type=Path, default=Path("reports/ar_idm_anchor"))
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    traj = load(DATA, data_dir=args.data_dir)
    key_fit, key_eval = jax.random.split(jax.random.key(args.seed))
    trees, timing, results, lpd = {}, {}, {}, {}
    for name in MODELS:
        # The same fit key for both models: their prior draws differ in dimension anyway.
        trees[name], timing[name] = fitted(key_fit, traj, name, args.out, args.seed)
        print(f"{name}: fit {timing[name]}", flush=True)
    scenarios = evaluation_scenarios(traj, HORIZON_S, 1)
    follower = {s.scenario_id: s.simulated_ids[0] for s in scenarios.scenarios}
    per_scenario = {}
    for name in MODELS:
        started = time.perf_counter()
        # The same evaluation key for both: common random numbers make the pairing tighter.
        results[name] = evaluate(
            key_eval,
            traj,
            model=name,
            posterior=trees[name],
            horizon_s=HORIZON_S,
            num_rollouts=args.rollouts,
            vehicles_per_scenario=1,
            seed=args.seed,
        )
        per_scenario[name] = pd.Series(
            {row["scenario"]: row["rmse_position_m"] for row in results[name]["by_scenario"]}
        )
        print(
            f"{name}: evaluated {len(per_scenario[name])} scenarios in "
            f"{time.perf_counter() - started:.0f} s, RMSE(3 s) "
            f"{results[name]['rmse_position_m']['mean']:.3f} m",
            flush=True,
        )
        lpd[name] = heldout_lpd(trees[name], name, traj)

    base, ar = MODELS
    scen = pd.DataFrame({m: per_scenario[m] for m in MODELS}).dropna()
    scen["vehicle"] = [follower[s] for s in scen.index]
    scen["difference"] = scen[ar] - scen[base]
    # Per vehicle: root mean square over its windows (each window's value is already an RMSE
    # over rollouts at 3 s).
    veh = scen.groupby("vehicle")[list(MODELS)].agg(lambda x: float(np.sqrt(np.mean(x**2))))
    veh["difference"] = veh[ar] - veh[base]
    veh["windows"] = scen.groupby("vehicle").size()
    lpd_frame = pd.DataFrame({f"lpd_{m}": lpd[m] for m in MODELS})
    lpd_frame["lpd_difference"] = lpd_frame[f"lpd_{ar}"] - lpd_frame[f"lpd_{base}"]
    veh = veh.join(lpd_frame, how="outer")
    n_fit = {m: int(trees[m]["posterior"]["vehicle"].size) for m in MODELS}
    summary = {
        "data": DATA,
        "seed": args.seed,
        "engine": "smc (defaults)",
        "horizon_s": HORIZON_S,
        "rollouts": args.rollouts,
        "vehicles_fitted": n_fit,
        "timing": timing,
        "per_vehicle_fit_s": {
            m: (timing[m]["wall_time_s"] + timing[m]["compile_time_s"]) / n_fit[m] for m in MODELS
        },
        "scenarios": len(scen),
        "vehicles_scored": int(veh["windows"].notna().sum()),
        "rmse_3s_mean_over_windows": {m: float(scen[m].mean()) for m in MODELS},
        "rmse_3s_pooled": {m: float(np.sqrt(np.mean(scen[m] ** 2))) for m in MODELS},
        "rmse_3s_library": {m: results[m]["rmse_position_m"]["mean"] for m in MODELS},
        "paper_mae_last_step": {
            m: results[m]["paper_mae_last_step"]["position_m"]["mean"] for m in MODELS
        },
        "difference_by_window": paired_interval(scen["difference"].to_numpy()),
        "difference_by_vehicle": paired_interval(veh["difference"].to_numpy()),
        "heldout_lpd_difference_by_vehicle": paired_interval(
            lpd_frame["lpd_difference"].to_numpy()
        ),
        "heldout_lpd_total": {m: float(lpd[m][np.isfinite(lpd[m])].sum()) for m in MODELS},
        "collisions": {m: results[m]["collisions"] for m in MODELS},
        "skipped": {m: results[m]["skipped"] for m in MODELS},
        "split_rule": results[base]["split_rule"],
        "scenario_rule": results[base]["scenario_set"],
    }
    write_text_atomic(args.out / "ar_idm_per_scenario.csv", scen.to_csv(index_label="scenario"))
    write_text_atomic(args.out / "ar_idm_per_vehicle.csv", veh.to_csv(index_label="vehicle"))
    write_text_atomic(args.out / "ar_idm_anchor.json", json.dumps(summary, indent=2, default=str))
    print(json.dumps(summary, indent=2, default=str), flush=True)


if __name__ == "__main__":
    main()
