"""Coverage of the latent-state engine on video-noise data bayesdrive did not make.

Issue #16, Deliver 3: with noisy positions and speeds derived from them, a latent-state fit
should recover the driver parameters. Per replication:

1. ``trafficgen`` (which imports nothing from bayesdrive: its own sub-stepped IDM) simulates one
   platoon of ``--followers`` followers behind a scripted head, ``--duration`` s, no cut-ins, with
   its ``video_position_noise`` mechanism at size ``--size``: white noise on every recorded
   position, speeds and headways derived from the noisy positions by differencing. It writes the
   NGSIM file; bayesdrive reads it as a user would (``read(..., format="ngsim_raw")``).
2. Every follower is fitted on every usable step (``window="all"``) by the engines of
   ``--engines`` (row labels, default all three), with their documented defaults and one key per
   replication and engine:
   - ``pmmh``: the latent-state engine on the IDM with measurement noise
     (``with_measurement_noise(IDM)``), all six IDM parameters and ``sigma_obs``;
   - ``smc``: the exact-state IDM, which takes the derived readings as true states: the negative
     control, expected to miss ``sigma`` (it must absorb the position noise as acceleration noise);
   - ``nuts-video``: ``nuts`` on ``idm+video_noise`` (``with_video_noise(IDM)``: the same seven
     parameters, the likelihood from an extended Kalman filter over the latent offset and speed).
3. For each follower and parameter: is the generator's truth (``Recording.params``; the position
   noise sd for ``sigma_obs``) inside the central 50% and 90% posterior intervals?

Coverage per engine and parameter over all followers, with Wilson 95% intervals; followers of one
replication share the head and the key, so the intervals are a little optimistic. The truth lies
inside the IDM's prior box (trafficgen's ``DRIVER_RANGES`` and sizes against the model's bounds,
checked at start). Model mismatch is real and intended: the generator integrates on 0.01 s
sub-steps, the model steps once per 0.1 s sample, and the leader's speed that the model reads is
itself differenced from noisy positions.

Seeds: replication r uses ``STUDY_SEEDS.start + r - 1`` (410001, ...), fixed before the study ran
and never used while developing this script; ``--dev`` uses ``DEV_SEEDS`` (490001, ...). Rows are
appended to ``coverage_runs.csv`` (resumable: a seed whose rows for every engine asked for carry
this library's fingerprint is skipped; rows are bit-reproducible within one installation); the
table is redrawn from them.

Run: ``python benchmarks/bench_latent_coverage.py --size small`` (and ``--size large``).
``--loglik-noise`` instead measures the state filter's log-likelihood noise at the truth on the
size's first seed (``coverage_loglik_noise.csv``). Writes ``coverage_runs.csv`` and
``coverage.md`` in ``reports/latent/`` (or ``--out``).
"""

from __future__ import annotations

import argparse
import inspect
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import arviz as az
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from rich.progress import track

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench_detection import append_rows, library_fingerprint, wilson  # noqa: E402
from bench_latent import markdown_table  # noqa: E402

from bayesdrive.data.atomic import write_atomic, write_text_atomic  # noqa: E402
from bayesdrive.data.readers import read  # noqa: E402
from bayesdrive.data.views import follower_arrays  # noqa: E402
from bayesdrive.drivers.base import fill_params  # noqa: E402
from bayesdrive.drivers.idm import IDM  # noqa: E402
from bayesdrive.drivers.measurement_noise import with_measurement_noise  # noqa: E402
from bayesdrive.drivers.video_noise import with_video_noise  # noqa: E402
from bayesdrive.inference.engines import smc  # noqa: E402, F401  (in the fingerprint)
from bayesdrive.inference.engines.pmmh import latent_data, state_filter_loglik  # noqa: E402
from bayesdrive.inference.engines.pmmh import run as run_pmmh  # noqa: E402
from bayesdrive.inference.fit import fit  # noqa: E402
from trafficgen import generate  # noqa: E402
from trafficgen.mechanisms import MECHANISMS  # noqa: E402
from trafficgen.simulate import DRIVER_RANGES  # noqa: E402

STUDY_SEEDS = range(410001, 411001)
DEV_SEEDS = range(490001, 491001)
MECHANISM = "video_position_noise"
NOISY_IDM = with_measurement_noise(IDM)
VIDEO_IDM = with_video_noise(IDM)
# Row label -> (model, engine), in the order their keys are split from the replication's seed.
ENGINES = {
    "pmmh": (NOISY_IDM, "pmmh"),
    "smc": (IDM, "smc"),
    "nuts-video": (VIDEO_IDM, "nuts"),
}
# trafficgen's names for the IDM's parameters, and the position noise for sigma_obs
TRUTH_NAMES = {
    "v_des": "v0",
    "d_min": "s0",
    "tau": "T",
    "a_max": "a",
    "b_pref": "b",
    "sigma": "sigma",
    "sigma_obs": f"{MECHANISM}.position_noise_m",
}
LEVELS = (0.5, 0.9)
STATE_PARTICLES = (32, 128, 512)
DEFAULT_STATE_PARTICLES = inspect.signature(run_pmmh).parameters["num_state_particles"].default
LOGLIK_KEYS = 32
CODE = library_fingerprint()  # taken once the engines are imported: the rows carry this version
FIELDS = [
    "seed",
    "size",
    "engine",
    "vehicle",
    "parameter",
    "truth",
    "median",
    "rhat",
    *(f"in_{round(100 * level)}" for level in LEVELS),
    "seconds",
    "code",
]


def check_truth_in_prior(size: str) -> None:
    """The generator's ranges must lie inside the model's prior box, or coverage fails by design."""
    ranges = DRIVER_RANGES | {TRUTH_NAMES["sigma_obs"]: MECHANISMS[MECHANISM].sizes[size]}
    for name, source in TRUTH_NAMES.items():
        spec = NOISY_IDM.spec(name)
        low, high = ranges[source]
        if not spec.lower <= low <= high <= spec.upper:
            raise SystemExit(
                f"trafficgen's {source} range {low}-{high} leaves {name}'s prior box "
                f"{spec.lower}-{spec.upper}: coverage would fail by construction"
            )


def recorded(seed: int, size: str, args: argparse.Namespace, workdir: Path):
    """trafficgen's recording of one replication and bayesdrive's reading of its file."""
    path = workdir / f"video_{size}_{seed}.csv"
    recording = generate(
        seed,
        path,
        {MECHANISM: MECHANISMS[MECHANISM].sizes[size]},
        platoons=1,
        followers=args.followers,
        duration_s=args.duration,
        cut_ins=0,
    )
    traj = read(path, format="ngsim_raw")
    path.unlink()
    return recording, traj


def truth_of(recording, vehicle: str, names: tuple[str, ...]) -> np.ndarray | None:
    """The generator's values of ``names`` for a follower (None for a head)."""
    rows = {str(v): i for i, v in enumerate(recording.vehicle_id) if recording.follower[i]}
    row = rows.get(str(vehicle).split(":")[-1])
    if row is None:
        return None
    return np.array([recording.params[TRUTH_NAMES[name]][row] for name in names])


def loglik_noise(seed: int, size: str, args: argparse.Namespace, workdir: Path) -> list[dict]:
    """The sd of the state filter's log-likelihood estimate at each follower's true parameters,
    over ``LOGLIK_KEYS`` keys, for each of ``STATE_PARTICLES`` (PMMH mixes when it is about 1-1.7
    nats, Doucet et al. 2015), with kappa = var N / T as in ``bench_latent.py``."""
    recording, traj = recorded(seed, size, args, workdir)
    arrays = follower_arrays(traj, window="all")
    observations, inputs = latent_data(arrays, NOISY_IDM)
    rows = []
    for index, vehicle in enumerate(arrays.vehicle_ids):
        truth = truth_of(recording, vehicle, NOISY_IDM.param_names)
        if truth is None:
            continue
        params = fill_params(NOISY_IDM, NOISY_IDM.param_names, jnp.asarray(truth, jnp.float32))
        one = jax.tree.map(lambda a, i=index: a[i], (observations, inputs))
        steps = int(one[0].mask.sum())
        for particles in STATE_PARTICLES:
            # One key per follower and particle count: no two estimates share randomness.
            own = jax.random.fold_in(jax.random.fold_in(jax.random.key(seed), index), particles)
            keys = jax.random.split(own, LOGLIK_KEYS)
            sd = float(np.std(np.asarray(_estimates(keys, params, one, particles))))
            rows.append(
                {
                    "size": size,
                    "seed": seed,
                    "vehicle": str(vehicle),
                    "position noise (m)": float(truth[-1]),
                    "steps": steps,
                    "state particles": particles,
                    "log-likelihood sd": sd,
                    "kappa": sd**2 * particles / steps,
                }
            )
    return rows


@partial(jax.jit, static_argnums=3)
def _estimates(keys, params, series, particles: int):
    """The filter's log-likelihood estimates of one vehicle's ``series``, one per key."""
    return jax.vmap(lambda k: state_filter_loglik(k, NOISY_IDM, params, *series, particles)[0])(
        keys
    )


def replicate(seed: int, size: str, args: argparse.Namespace, workdir: Path) -> list[dict]:
    """One replication: simulate, write, read, fit by both engines, score the intervals."""
    recording, traj = recorded(seed, size, args, workdir)
    # split(key, 3) begins with split(key, 2): the first two engines keep their earlier keys.
    keys = dict(zip(ENGINES, jax.random.split(jax.random.key(seed), len(ENGINES)), strict=True))
    rows = []
    for label in args.engines:
        model, engine = ENGINES[label]
        key = keys[label]
        started = time.perf_counter()
        tree = fit(key, traj, model=model, engine=engine, window="all", seed=seed)
        seconds = time.perf_counter() - started
        posterior = tree["posterior"]
        for vehicle in posterior["vehicle"].values:
            truths = truth_of(recording, vehicle, model.param_names)
            if truths is None:  # a head: replayed, not a simulated driver
                continue
            for name, truth in zip(model.param_names, truths, strict=True):
                truth = float(truth)
                chains = posterior[name].sel(vehicle=vehicle).values  # (chain, draw)
                draws = chains.ravel()
                inside = {
                    f"in_{round(100 * level)}": int(
                        np.quantile(draws, (1 - level) / 2)
                        <= truth
                        <= np.quantile(draws, (1 + level) / 2)
                    )
                    for level in LEVELS
                }
                rows.append(
                    {
                        "seed": seed,
                        "size": size,
                        "engine": label,
                        "vehicle": str(vehicle),
                        "parameter": name,
                        "truth": truth,
                        "median": float(np.median(draws)),
                        "rhat": float(az.rhat(chains)) if chains.shape[0] > 1 else np.nan,
                        **inside,
                        "seconds": round(seconds, 1),
                        "code": CODE,
                    }
                )
    return rows


def coverage_table(runs: pd.DataFrame) -> pd.DataFrame:
    """Coverage per (size, engine, parameter) with Wilson intervals."""
    records = []
    for (size, engine, name), group in runs.groupby(["size", "engine", "parameter"], sort=False):
        record = {
            "size": size,
            "engine": engine,
            "parameter": name,
            "followers": len(group),
            "replications": group["seed"].nunique(),
        }
        for level in LEVELS:
            column = f"in_{round(100 * level)}"
            low, high = wilson(int(group[column].sum()), len(group))
            record[f"{column} rate"] = f"{group[column].mean():.2f}"
            record[f"{column} 95% interval"] = f"[{low:.2f}, {high:.2f}]"
        rhat = group["rhat"].dropna()
        record["R-hat < 1.05"] = f"{(rhat < 1.05).mean():.2f}" if len(rhat) else "-"
        record["median abs error"] = f"{(group['median'] - group['truth']).abs().median():.3g}"
        records.append(record)
    return pd.DataFrame(records)


def recovery_figure(runs: pd.DataFrame, path: Path) -> None:
    """Posterior median against the generator's truth, one panel per parameter, one colour per
    engine and a marker per size: points on the diagonal are recovered parameters."""
    names = list(dict.fromkeys(runs["parameter"]))
    columns = 4
    rows_of_panels = -(-len(names) // columns)
    fig, axes = plt.subplots(
        rows_of_panels, columns, figsize=(3.2 * columns, 3.0 * rows_of_panels), squeeze=False
    )
    markers = {"small": "o", "large": "^"}
    for axis, name in zip(axes.flat, names, strict=False):
        rows = runs[runs["parameter"] == name]
        for (engine, size), group in rows.groupby(["engine", "size"], sort=False):
            axis.scatter(
                group["truth"],
                group["median"],
                s=12,
                marker=markers.get(size, "o"),
                color=f"C{list(ENGINES).index(engine)}",
                alpha=0.7,
                label=f"{engine} ({size})",
            )
        low = min(rows["truth"].min(), rows["median"].min())
        high = max(rows["truth"].max(), rows["median"].max())
        axis.plot([low, high], [low, high], color="0.5", lw=0.8)
        if name == "sigma_obs":
            axis.set_xscale("log")
            axis.set_yscale("log")
        axis.set_title(name)
        axis.set_xlabel("truth")
        axis.set_ylabel("posterior median")
    handles = {}
    for axis in axes.flat[: len(names)]:
        for handle, label in zip(*axis.get_legend_handles_labels(), strict=True):
            handles.setdefault(label, handle)
    legend_axis = axes.flat[len(names)] if len(names) < axes.size else axes.flat[-1]
    legend_axis.legend(handles.values(), handles.keys(), loc="center", fontsize=8)
    for axis in axes.flat[len(names) :]:
        axis.axis("off")
    fig.tight_layout()
    write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    plt.close(fig)


def loglik_noise_path(runs_path: Path) -> Path:
    """The ``--loglik-noise`` rows beside the coverage rows (study or dev)."""
    return runs_path.with_name(runs_path.name.replace("runs", "loglik_noise"))


def write_report(runs_path: Path, out: Path) -> str:
    runs = pd.read_csv(runs_path)
    seeds = sorted(runs["seed"].unique())
    codes = ", ".join(sorted(runs["code"].unique()))
    table = coverage_table(runs)
    seconds = runs.drop_duplicates(["seed", "engine"]).groupby("engine")["seconds"].median()
    text = "\n".join(
        [
            "# The latent-state engine on video-noise data from the independent generator",
            "",
            "Generated by `benchmarks/bench_latent_coverage.py` from `coverage_runs.csv` "
            f"(library {codes}; seeds {seeds[0]}-{seeds[-1]}, {len(seeds)} replications, fixed "
            "before the run). Protocol in the script's docstring: trafficgen's video position "
            "noise (speeds and headways differenced from noisy positions), every follower fitted "
            "on all its usable steps by `pmmh` (IDM with measurement noise), by `smc` (exact-"
            "state IDM, the negative control) and by `nuts` on `idm+video_noise` (`nuts-video`: "
            "the Kalman-filter likelihood), engine defaults; a row counts followers whose "
            "true parameter lies inside the central 50% / 90% posterior interval. Wilson 95% "
            "intervals treat followers as independent (those of one replication share a head "
            "and a key).",
            "",
            "Median seconds per replication and engine: "
            + ", ".join(f"{e} {s:.0f}" for e, s in seconds.items())
            + ".",
            "",
            markdown_table(table.to_dict("records"), list(table.columns)),
            "",
        ]
    )
    noise_path = loglik_noise_path(runs_path)
    if noise_path.exists():
        noise = pd.read_csv(noise_path)
        text += "\n".join(
            [
                "",
                "## Noise of the state filter's log-likelihood estimate at the truth",
                "",
                f"`--loglik-noise`: each follower of the first seed of each size, at its true "
                f"parameters; sd over {LOGLIK_KEYS} keys, kappa = var N / T. PMMH mixes when "
                "the sd is about 1-1.7 nats (Doucet et al. 2015); the engine's default is "
                f"{DEFAULT_STATE_PARTICLES} state particles.",
                "",
                markdown_table(noise.to_dict("records"), list(noise.columns)),
                "",
            ]
        )
    recovery_figure(runs, out / "coverage_recovery.png")
    text += "\n![posterior median against truth](coverage_recovery.png)\n"
    write_text_atomic(out / "coverage.md", text)
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--replications", type=int, default=10)
    parser.add_argument("--size", choices=tuple(MECHANISMS[MECHANISM].sizes), default="small")
    parser.add_argument("--followers", type=int, default=2)
    parser.add_argument("--duration", type=float, default=40.0, help="seconds per record")
    parser.add_argument("--dev", action="store_true", help="development seeds and files")
    parser.add_argument(
        "--engines",
        type=lambda text: tuple(text.split(",")),
        default=tuple(ENGINES),
        help=f"comma-separated row labels to fit, of {', '.join(ENGINES)}",
    )
    parser.add_argument("--out", type=Path, default=ROOT / "reports" / "latent")
    parser.add_argument("--report-only", action="store_true", help="redraw the table from the CSV")
    parser.add_argument(
        "--stop-at", type=float, default=None, help="start no replication after this Unix time"
    )
    parser.add_argument(
        "--loglik-noise",
        action="store_true",
        help="measure the filter's estimate noise on the size's first seed instead of fitting",
    )
    args = parser.parse_args(argv)
    unknown = sorted(set(args.engines) - set(ENGINES))
    if unknown:
        parser.error(f"unknown engine label(s) {unknown}; known: {list(ENGINES)}")
    args.out.mkdir(parents=True, exist_ok=True)
    runs_path = args.out / ("coverage_dev_runs.csv" if args.dev else "coverage_runs.csv")
    if args.report_only:
        print(write_report(runs_path, args.out))
        return 0
    seeds = (DEV_SEEDS if args.dev else STUDY_SEEDS)[: args.replications]
    if args.loglik_noise:
        noise_path = loglik_noise_path(runs_path)
        with tempfile.TemporaryDirectory() as tmp:
            rows = loglik_noise(seeds[0], args.size, args, Path(tmp))
        if noise_path.exists():
            previous = pd.read_csv(noise_path)
            rows = [*previous[previous["size"] != args.size].to_dict("records"), *rows]
        write_text_atomic(noise_path, pd.DataFrame(rows).to_csv(index=False))
        if runs_path.exists():
            print(write_report(runs_path, args.out))
        return 0
    check_truth_in_prior(args.size)
    done = set()
    if runs_path.exists():
        previous = pd.read_csv(runs_path)
        mine = previous[
            (previous["size"] == args.size)
            & (previous["code"] == CODE)
            & previous["engine"].isin(args.engines)
        ]
        # A replication is done when every engine asked for has its rows at this library.
        done = {
            seed
            for seed, group in mine.groupby("seed")
            if set(args.engines) <= set(group["engine"])
        }
    todo = [seed for seed in seeds if seed not in done]
    print(f"{len(done)} replications done, {len(todo)} to go", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for seed in track(todo, description=f"video noise {args.size}"):
            if args.stop_at is not None and time.time() > args.stop_at:
                print("stopped at --stop-at", flush=True)
                break
            append_rows(runs_path, replicate(seed, args.size, args, Path(tmp)), FIELDS)
    if runs_path.exists():
        print(write_report(runs_path, args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
