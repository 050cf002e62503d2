"""At which sampling rate should the criticism work? The autocorrelated noise and the reaction
delay on real data at 10 Hz and subsampled to 2 Hz.

Why: at 10 Hz on smoothed trajectories (NGSIM I-80's chains were EMD-smoothed, OpenACC's positions
spline-interpolated from 3-5 Hz fixes) the one-step (0.1 s) density rewards a residual that is
nearly a random walk: the autocorrelated noise's coefficient goes to 0.97-0.99 and soaks up the
IDM's error in level, and the loop named a cause whose closed-loop forecast was worse. Over 0.5 s
steps the smoothing's correlation has mostly decayed.

Protocol (fixed before the run): the criticism's data of ``bayesdrive reproduce`` (its full
settings: the scenes ``experiments.paper.criticised_scenes`` names of NGSIM I-80 chains and
OpenACC's human recordings, their first ``criticism_seconds``; the run of
``reports/sampling_rate.md`` read NGSIM I-80's first 8 scenes, the settings then), every sample (10 Hz) and every fifth (2 Hz,
:meth:`~bayesdrive.data.trajectories.Trajectories.every`). At each rate one round of
``criticize`` (the reproduction's particles and rollouts, seed 20261127) with the family
``autocorrelated_noise`` and ``reaction_delay``, both fitted whatever the screening says
(``screen_p`` infinite), so their gains exist at both rates. Per data set and rate: the one-step
held-out gain of each cause over the IDM (nats, SE, Holm-adjusted significance), its 5 s
forecast gain (energy score of the (gap, speed) path from the filtered start, paired across
vehicles), the predictive-mean RMSE change and collisions; the autocorrelated noise's correlation
time ``noise_time_s`` and its per-step coefficient rho = T / (T + dt).

Decision rule (fixed before the run): the criticism works at the rate at which, on both data sets,
the sign of each cause's one-step gain agrees with the sign of its forecast gain (the one-step
score names what also forecasts better); where both rates qualify, 10 Hz (five times the steps);
where neither does, the report says so and the rate stays 10 Hz.

Writes ``reports/sampling_rate.md`` and ``reports/sampling_rate.json``.
Run: ``PYTHONPATH=. python benchmarks/bench_sampling_rate.py``
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bayesdrive.criticism.criticize import CriticizeConfig, criticize  # noqa: E402
from bayesdrive.data.atomic import write_text_atomic  # noqa: E402
from bayesdrive.data.provenance import provenance_line  # noqa: E402
from bayesdrive.experiments.paper import FULL, criticism_data, highway_data  # noqa: E402

SEED = 20261127
FACTORS = {"10 Hz": 1, "2 Hz": 5}
CAUSES = ("autocorrelated_noise", "reaction_delay")
DATA = ("ngsim_i80_chains", "openacc_vicolungo:human")


def criticised(label: str):
    """The reproduction's criticism data for ``label`` (``experiments.paper.criticism_data``)."""
    return criticism_data(label, highway_data(label.split(":")[0])[label], FULL)


def cause_row(entry: dict, dt: float) -> dict:
    gain, forecast = entry["gain"], entry["forecast"] or {}
    row = {
        "one_step_gain": gain["elpd"],
        "one_step_se": gain["se"],
        "one_step_significant": gain["significant"],
        "forecast_gain": forecast.get("energy_score_gain"),
        "forecast_se": forecast.get("energy_score_gain_se"),
        "forecast_p": forecast.get("p_value"),
        "rmse_change_m": forecast.get("rmse_mean_position_change_m"),
        "collisions": forecast.get("collisions"),
        "collisions_idm": forecast.get("collisions_current"),
    }
    for name in ("noise_time_s", "noise_lag_s"):
        posterior = entry.get("posterior", {}).get(name)
        if posterior:
            # Across vehicles: the mean of the per-vehicle posterior means, and its 5%-95% range.
            row[name] = [posterior["mean"], posterior["q05_vehicles"], posterior["q95_vehicles"]]
    if "noise_time_s" in row:
        row["rho"] = [t / (t + dt) for t in row["noise_time_s"]]
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "reports")
    args = parser.parse_args(argv)
    config = CriticizeConfig(
        num_particles=FULL.criticism_particles,
        num_rollouts=FULL.criticism_rollouts,
        max_rounds=1,
        causes=CAUSES,
        screen_p=float("inf"),  # fit both causes whatever the screening checks say
    )
    results = []
    for label in DATA:
        traj = criticised(label)
        for rate, factor in FACTORS.items():
            data = traj.every(factor)
            started = time.perf_counter()
            result = criticize(data, seed=SEED, config=config, progress=print)
            report = result.report
            entries = {e["name"]: e for e in report["causes"]}
            results.append(
                {
                    "data": label,
                    "rate": rate,
                    "dt_s": data.dt,
                    "vehicles": report["data"]["vehicles"],
                    "scored_steps_fit": report["data"]["scored_steps_fit"],
                    "scored_steps_heldout": report["data"]["scored_steps_heldout"],
                    "base_energy_score": report["base"]["energy_score"],
                    "named": report["rounds"][0]["named"],
                    "adopted": report["adopted"],
                    "causes": {c: cause_row(entries[c], data.dt) for c in CAUSES},
                    "seconds": time.perf_counter() - started,
                }
            )
            print(f"{label} at {rate}: {time.perf_counter() - started:.0f} s", flush=True)
    agree = {
        rate: all(
            (r["causes"][c]["one_step_gain"] > 0) == (r["causes"][c]["forecast_gain"] > 0)
            for r in results
            if r["rate"] == rate
            for c in CAUSES
        )
        for rate in FACTORS
    }
    chosen = "10 Hz" if agree["10 Hz"] or not agree["2 Hz"] else "2 Hz"
    record = {
        "seed": SEED,
        "settings": {**config._asdict(), "causes": list(CAUSES)},
        "results": results,
        "signs_agree": agree,
        "chosen_rate": chosen,
        "provenance": provenance_line(),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out / "sampling_rate.json", json.dumps(record, indent=2))
    write_text_atomic(args.out / "sampling_rate.md", markdown(record))
    print(markdown(record))
    return 0


def _number(value, digits: int = 3) -> str:
    return "--" if value is None else f"{value:.{digits}g}"


def markdown(record: dict) -> str:
    lines = [
        "# The criticism's sampling rate: 10 Hz against 2 Hz (benchmarks/bench_sampling_rate.py)",
        "",
        f"{record['provenance']}. Protocol and decision rule: the script's docstring (fixed "
        f"before the run). Seed {record['seed']}; one round of `criticize` with the family "
        f"{', '.join(f'`{c}`' for c in CAUSES)}, both fitted at both rates.",
        "",
        "Gains are the IDM's score minus the extension's: positive means the extension is "
        "better. One-step: held-out log predictive density summed over vehicles (nats, SE across "
        "vehicles). Forecast: mean over vehicles of the 5 s energy score's decrease (SE, one-sided "
        "p). RMSE: change of the predictive mean's position RMSE (m, negative is better).",
        "",
        "| data | rate | vehicles | steps (fit / held-out) | cause | one-step gain (SE) | "
        "forecast gain (SE, p) | RMSE change (m) | collisions (IDM) | noise_time_s: mean of the "
        "vehicles' posterior means (5%-95% over vehicles); rho = T / (T + dt) at those T | "
        "noise_lag_s: the same |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in record["results"]:
        for cause, c in r["causes"].items():
            ar = (
                "{:.2f} s ({:.2f}-{:.2f}), rho {:.3f} ({:.3f}-{:.3f})".format(
                    *c["noise_time_s"], *c["rho"]
                )
                if "noise_time_s" in c
                else ""
            )
            lag = "{:.2f} s ({:.2f}-{:.2f})".format(*c["noise_lag_s"]) if "noise_lag_s" in c else ""
            lines.append(
                f"| {r['data']} | {r['rate']} | {r['vehicles']} | {r['scored_steps_fit']} / "
                f"{r['scored_steps_heldout']} | {cause} | {_number(c['one_step_gain'], 4)} "
                f"({_number(c['one_step_se'])}) | {_number(c['forecast_gain'])} "
                f"({_number(c['forecast_se'])}, {_number(c['forecast_p'], 2)}) | "
                f"{_number(c['rmse_change_m'])} | {c['collisions']} ({c['collisions_idm']}) | "
                f"{ar} | {lag} |"
            )
    lines += [
        "",
        "Named and adopted by the round: "
        + "; ".join(
            f"{r['data']} at {r['rate']}: named {r['named']}, adopted {r['adopted'] or 'nothing'}"
            for r in record["results"]
        )
        + ".",
        "",
        "Signs of the one-step and forecast gains agree for every cause on both data sets: "
        + ", ".join(f"{rate} {'yes' if ok else 'no'}" for rate, ok in record["signs_agree"].items())
        + f". By the decision rule the criticism works at **{record['chosen_rate']}**.",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
