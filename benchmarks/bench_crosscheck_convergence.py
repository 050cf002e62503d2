"""Do the cross-checks (nuts, emcee) pass their own convergence checks at their defaults, and agree
with smc? Writes ``reports/convergence.md``.

Data: the independent generator's (``trafficgen``) platoons, ``--followers`` followers (platoons of
six, no cut-ins) of ``--duration`` seconds, written as NGSIM raw and read back, one data set per
model fitted:

* ``idm``: plain IDM drivers with white noise, fitted by ``idm``;
* ``autocorrelated_noise``: Ornstein-Uhlenbeck pedal noise (``pedal_noise``), fitted by
  ``idm+autocorrelated_noise``;
* ``reaction_delay``: delayed perception (``perception_delay``), fitted by ``idm+reaction_delay``;
* the other causes the criticism can adopt, each on the mechanism that its right verdict names
  (``trafficgen.MECHANISMS``, medium sizes): ``speed_dependent_noise`` (``speed_power_noise``),
  ``drifting_parameters`` (``time_gap_drift``), ``measurement_noise`` (``video_position_noise``),
  ``second_leader_anticipation`` (``two_leader_anticipation``),
  ``leader_acceleration_anticipation`` (``leader_acceleration_response``) and
  ``cut_in_overreaction`` (``cut_in_relaxation``, with cut-ins), each fitted by ``idm+<cause>``;
* ``ngsim_agreement`` (only when asked for with ``--data``): real data, the 15 NGSIM I-80 followers
  of ``benchmarks/bench_agreement.py`` (its choice rule, fitting windows), fitted by ``idm``;
  ``ngsim_agreement+<cause>`` fits ``idm+<cause>`` to the same followers (the issue asks every
  adoptable extension of them).

Every data set is fitted by ``bayesdrive.inference.fit.fit`` at its defaults (all parameters, 1000
draws, seed ``--seed``) with smc, nuts and emcee; with the engines as they were before extension
(``nuts-before``: ``max_extension=1``; ``emcee-before``: ``max_steps=4000``), the study of why they
failed; with emcee's differential-evolution moves (``emcee-de``); and with nuts, unextended, given
a dense mass matrix (``nuts-dense``) or 4000 draws after 1000 warm-up (``nuts-4x``). Per run: the
convergence problems fit reports (exit 3 when any), wall time, extension factors; per parameter:
vehicles failing, median R-hat and ESS, and how many posteriors press on a prior bound (1st or 99th
percentile within 2% of the box's width of its edge); agreement of each engine with smc
(``bayesdrive.inference.diagnostics.agreement``).

Runs are independent jobs; ``--jobs N`` runs N at once (processes; each uses the cores JAX
gives it). The full study (24 followers of 60 s, every data set but the NGSIM one, eight runs each)::

    python benchmarks/bench_crosscheck_convergence.py --jobs 16 --out reports
"""

from __future__ import annotations

import argparse
import concurrent.futures
import multiprocessing
import os
import sys
import tempfile
import time
from pathlib import Path

# trafficgen is not installed with bayesdrive: it lives at the repository root beside it.
ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

# Each data set: (trafficgen mechanism and its size range, the model fitted to it).
DATA = {
    "idm": (None, "idm"),
    "autocorrelated_noise": ({"pedal_noise": (0.5, 0.8)}, "idm+autocorrelated_noise"),
    "reaction_delay": ({"perception_delay": (0.4, 0.7)}, "idm+reaction_delay"),
    "speed_dependent_noise": ({"speed_power_noise": (0.5, 1.0)}, "idm+speed_dependent_noise"),
    "drifting_parameters": ({"time_gap_drift": (0.2, 0.35)}, "idm+drifting_parameters"),
    "measurement_noise": ({"video_position_noise": (0.01, 0.03)}, "idm+measurement_noise"),
    "second_leader_anticipation": (
        {"two_leader_anticipation": (0.3, 0.5)},
        "idm+second_leader_anticipation",
    ),
    "leader_acceleration_anticipation": (
        {"leader_acceleration_response": (0.25, 0.5)},
        "idm+leader_acceleration_anticipation",
    ),
    "cut_in_overreaction": ({"cut_in_relaxation": (0.4, 0.7)}, "idm+cut_in_overreaction"),
}
# Cut-ins of a data set (the others have none: platoons of followers only).
CUT_INS = {"cut_in_overreaction": 8}
# Real data: the 15 NGSIM I-80 followers of benchmarks/bench_agreement.py (its choice rule, their
# fitting windows), fitted by the IDM; ``--followers`` does not apply to them.
NGSIM = "ngsim_agreement"
NGSIM_VEHICLES = 15
# Each run: (engine, engine options); the "-before" runs are the engines without extension.
RUNS = {
    "smc": ("smc", {}),
    # One vehicle per compiled chunk, so each prints its progress as it finishes (same bits).
    "nuts": ("nuts", {"vehicle_chunk": 1}),
    "emcee": ("emcee", {}),
    "nuts-before": ("nuts", {"max_extension": 1}),
    "emcee-before": ("emcee", {"max_steps": 4000}),
    "emcee-de": ("emcee", {"move": "de"}),
    # The suspects of the study, one at a time, without extension: a dense mass matrix; 4x draws.
    "nuts-dense": ("nuts", {"dense_mass": True, "max_extension": 1}),
    "nuts-4x": ("nuts", {"draws": 4000, "warmup": 1000, "max_extension": 1}),
}
PLATOON = 6
# What follows this line in the report is written by hand (the reading of the tables) and kept.
FINDINGS_MARKER = "<!-- findings: written by hand below, kept when the tables are regenerated -->"
BOUND_MARGIN = 0.02


def write_keeping_findings(target: Path, text: str) -> None:
    """Write a regenerated report atomically, keeping what follows :data:`FINDINGS_MARKER` in the
    one it replaces (the hand-written reading of the tables)."""
    from bayesdrive.data.atomic import write_text_atomic

    if target.exists() and FINDINGS_MARKER in target.read_text():
        text += "\n" + FINDINGS_MARKER + target.read_text().split(FINDINGS_MARKER, 1)[1]
    write_text_atomic(target, text)


def is_ngsim(data: str) -> bool:
    """Whether ``data`` names the NGSIM followers (``ngsim_agreement``, or with ``+<cause>``)."""
    return data == NGSIM or data.startswith(NGSIM + "+")


def generate_data(data: str, seed: int, followers: int, duration: float, folder: Path) -> Path:
    from trafficgen import generate

    path = folder / f"{data}.csv"
    if not path.exists():
        platoons = -(-followers // PLATOON)
        mechanisms, _ = DATA[data]
        generate(
            seed,
            path,
            mechanisms,
            platoons=platoons,
            followers=PLATOON,
            duration_s=duration,
            cut_ins=CUT_INS.get(data, 0),
        )
    return path


def one_run(data: str, run: str, seed: int, followers: int, duration: float, folder: str) -> dict:
    """Fit one data set with one run's engine; save the tree; return its row and diagnosis."""
    import jax

    from bayesdrive.data.readers import read
    from bayesdrive.drivers.idm import IDM
    from bayesdrive.drivers.registry import get_model
    from bayesdrive.inference.core.output import metadata, save_result
    from bayesdrive.inference.diagnostics.agreement import convergence_table
    from bayesdrive.inference.fit import fit

    if is_ngsim(data):
        from bayesdrive.data.registry import load
        from bayesdrive.data.views import follower_arrays
        from benchmarks.bench_agreement import DATA as AGREEMENT_DATA
        from benchmarks.bench_agreement import choose_vehicles

        traj = load(AGREEMENT_DATA)
        vehicles = choose_vehicles(traj, NGSIM_VEHICLES)
        if data == NGSIM:
            # Arrays, not a subset: a subset would drop the leaders whose speeds the followers need.
            data_in, limit = follower_arrays(traj, window="fit", vehicle_ids=vehicles), {}
            model = IDM
        else:  # an extension builds its own inputs (a scene, a second leader) from the recording
            data_in, limit = traj, {"vehicle_ids": vehicles}
            model = get_model("idm" + data.removeprefix(NGSIM))
    else:
        path = generate_data(data, seed, followers, duration, Path(folder))
        data_in, limit = read(path, format="ngsim_raw"), {"max_vehicles": followers}
        model = get_model(DATA[data][1])
    engine, options = RUNS[run]
    started = time.perf_counter()

    def progress(done: int, total: int) -> None:  # a run can take an hour: say where it is
        print(
            f"{data} {run}: {done}/{total} vehicles, {time.perf_counter() - started:.0f} s",
            flush=True,
        )

    tree = fit(
        jax.random.key(seed),
        data_in,
        model=model,
        engine=engine,
        seed=seed,
        progress=progress,
        **limit,
        **options,
    )
    wall = time.perf_counter() - started
    save_result(tree, Path(folder) / f"{data}-{run}.nc")
    problems = metadata(tree)["convergence"]["problems"]
    stats = tree["sample_stats"].to_dataset()
    if "extension" in stats:  # nuts
        extension = stats["extension"].values
    elif "num_steps" in stats:  # emcee: steps run over the steps asked for
        extension = stats["num_steps"].values // metadata(tree)["engine_options"]["num_steps"]
    else:
        extension = np.ones(tree["posterior"].sizes["vehicle"], dtype=int)
    row = {
        "data": data,
        "run": run,
        "model": model.name,
        "vehicles": tree["posterior"].sizes["vehicle"],
        "problems": len(problems),
        "exit": 3 if problems else 0,
        "vehicles_failing": len({p["vehicle"] for p in problems}),
        "wall_s": wall,
        "extension": {
            int(k): int(n) for k, n in zip(*np.unique(extension, return_counts=True), strict=True)
        },
        "divergences": int(stats["diverging"].values.sum()) if "diverging" in stats else None,
        "median_tau": float(np.median(stats["autocorr_time"].values))
        if "autocorr_time" in stats
        else None,
    }
    table = convergence_table(tree)
    posterior = tree["posterior"].to_dataset()
    bounds = {s.name: (s.lower, s.upper) for s in model.specs}
    failing = {(p["vehicle"], p["param"]) for p in problems}
    near_bound = []
    for r in table.itertuples():
        lower, upper = bounds[r.param]
        values = posterior[r.param].sel(vehicle=r.vehicle).values.ravel()
        q01, q99 = (np.quantile(values, [0.01, 0.99]) - lower) / (upper - lower)
        near_bound.append(q01 < BOUND_MARGIN or q99 > 1 - BOUND_MARGIN)
    table["near_bound"] = near_bound
    table["failing"] = [(r.vehicle, r.param) in failing for r in table.itertuples()]
    diagnosis = table.groupby("param", sort=False).agg(
        failing=("failing", "sum"),
        rhat=("rhat", "median"),
        ess_bulk=("ess_bulk", "median"),
        ess_tail=("ess_tail", "median"),
        near_bound=("near_bound", "sum"),
        failing_near_bound=("near_bound", lambda s: int((s & table.loc[s.index, "failing"]).sum())),
    )
    diagnosis.insert(0, "run", run)
    diagnosis.insert(0, "data", data)
    print(row, flush=True)
    return {"row": row, "diagnosis": diagnosis.reset_index()}


def markdown(frame: pd.DataFrame) -> str:
    def cell(value) -> str:
        return f"{value:.3g}" if isinstance(value, float | np.floating) else str(value)

    lines = [" | ".join(map(str, frame.columns)), " | ".join("---" for _ in frame.columns)]
    lines += [" | ".join(cell(v) for v in row) for row in frame.itertuples(index=False)]
    return "\n".join(f"| {line} |" for line in lines)


def agreement(data: str, runs: list[str], folder: Path) -> list[dict]:
    from bayesdrive.inference.core.output import load_result
    from bayesdrive.inference.diagnostics.agreement import agreement_table

    smc = load_result(folder / f"{data}-smc.nc")
    rows = []
    for run in runs:
        if run == "smc":
            continue
        table = agreement_table({"smc": smc, run: load_result(folder / f"{data}-{run}.nc")})
        rows.append(
            {
                "data": data,
                "run": run,
                "pairs": len(table),
                "agree": int(table["agree"].sum()),
                "agree_mean": int(table["agree_mean"].sum()),
                "agree_sd": int(table["agree_sd"].sum()),
                "max_abs_mean_diff_sd": float(table["mean_diff_sd"].abs().max()),
            }
        )
    return rows


def described(data_sets: list[str], args: argparse.Namespace) -> str:
    """The data of a run, in words, for the report's header."""
    parts = []
    if any(not is_ngsim(d) for d in data_sets):
        parts.append(
            f"trafficgen, {args.followers} followers of {args.duration:g} s per data set "
            f"(seed {args.seed})"
        )
    if any(is_ngsim(d) for d in data_sets):
        parts.append(
            f"the {NGSIM_VEHICLES} NGSIM I-80 followers of benchmarks/bench_agreement.py "
            "(fitting windows)"
        )
    return "; ".join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("reports"))
    parser.add_argument("--followers", type=int, default=24)
    parser.add_argument("--duration", type=float, default=60.0, help="seconds per follower")
    parser.add_argument(
        "--data", default=",".join(DATA), help=f"among {', '.join([*DATA, NGSIM])}, {NGSIM}+<cause>"
    )
    parser.add_argument("--runs", default=",".join(RUNS), help=f"among {', '.join(RUNS)}")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument(
        "--keep", type=Path, default=None, help="folder to keep the data and results in"
    )
    args = parser.parse_args(argv)
    data_sets, runs = args.data.split(","), args.runs.split(",")
    if "smc" not in runs:
        runs.insert(0, "smc")  # the reference of the agreement columns
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as scratch:
        tmp = str(args.keep or scratch)
        Path(tmp).mkdir(parents=True, exist_ok=True)
        for data in data_sets:  # written once, before the jobs read them
            if not is_ngsim(data):
                generate_data(data, args.seed, args.followers, args.duration, Path(tmp))
        jobs = [(data, run) for data in data_sets for run in runs]
        context = multiprocessing.get_context("spawn")
        with concurrent.futures.ProcessPoolExecutor(args.jobs, mp_context=context) as pool:
            futures = [
                pool.submit(one_run, d, r, args.seed, args.followers, args.duration, tmp)
                for d, r in jobs
            ]
            results = [f.result() for f in futures]
        agreements = [row for data in data_sets for row in agreement(data, runs, Path(tmp))]
    total = time.perf_counter() - started
    rows = pd.DataFrame([r["row"] for r in results])
    diagnosis = pd.concat([r["diagnosis"] for r in results], ignore_index=True)
    load = os.getloadavg()
    from bayesdrive.inference.diagnostics.agreement import CRITERION

    command = " ".join(sys.argv[1:] if argv is None else argv)
    text = "\n".join(
        [
            "# Convergence of the cross-checks (nuts, emcee) at their defaults",
            "",
            f"Generated by `python benchmarks/bench_crosscheck_convergence.py "
            f"{command}` ({os.cpu_count()} cores, load average at the end {load[0]:.1f}; "
            f"{total:.0f} s in all). Data: {described(data_sets, args)}; every run is `fit` at its "
            "defaults (1000 draws, all parameters, seed "
            f"{args.seed}); `nuts-before` and `emcee-before` are the engines without extension, "
            "`emcee-de` emcee with its differential-evolution moves, `nuts-dense` and `nuts-4x` "
            "nuts without extension with a dense mass matrix and with 4000 draws after 1000 "
            "warm-up.",
            "",
            "## Runs",
            "",
            "`problems`: failed checks (vehicle x parameter x check; R-hat 1.01, bulk and tail ESS "
            "400, emcee 50 tau); `exit`: the CLI's exit code; `extension`: vehicles per extension "
            "factor (emcee: steps run / 4000).",
            "",
            markdown(rows),
            "",
            "## Why they fail: per parameter",
            "",
            "Medians over vehicles. `near_bound`: vehicles whose posterior's 1st or 99th "
            f"percentile lies within {BOUND_MARGIN:.0%} of the prior box's width of an edge; "
            "`failing_near_bound`: of the failing ones.",
            "",
            markdown(diagnosis),
            "",
            "## Agreement with smc",
            "",
            "Per vehicle and parameter, `bayesdrive.inference.diagnostics.agreement`'s criterion: "
            f"{CRITERION}.",
            "",
            markdown(pd.DataFrame(agreements)),
            "",
        ]
    )
    args.out.mkdir(parents=True, exist_ok=True)
    write_keeping_findings(args.out / "convergence.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
