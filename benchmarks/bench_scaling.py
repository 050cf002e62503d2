"""Scaling of the exact engine (``smc``) with the number of vehicles: one process, vectorised
batches, and a 2-worker Dask ``LocalCluster``, on whatever JAX device the machine has.

Followers come from the independent generator (``trafficgen``: platoons of ten, no hidden
mechanism, ``--duration`` seconds each, generated once for the largest size) and are fitted on
their whole series with smc at its defaults (1000 particles, six IDM parameters). Each (mode,
size) runs in a fresh subprocess, so its peak resident memory is its own; the cluster mode
reports the largest worker's peak as well. Wall time is inference only (compilation reported
apart), so rows of different sizes compare the cost per vehicle. Modes:

* ``plain``: ``vehicle_batch=1``, vehicles one after another in compiled chunks, one JAX device;
* ``devices``: as ``plain`` with one JAX CPU device per core (what the ``bayesdrive`` command
  sets up): each chunk is split over the devices, the same bits as ``plain``;
* ``batched``: ``vehicle_batch=--batch`` vehicles vectorised together (``vmap``: ``lax.cond``
  becomes a select, so every step pays for a rejuvenation; a GPU has the width to absorb it);
* ``cluster``: ``fit_on_cluster`` on a ``LocalCluster`` of 2 one-core process workers, chunks of
  16 vehicles, start-up of the cluster included.

Rows are appended to ``<out>/runs.jsonl`` (a rerun skips the (machine, mode, size) rows already
there) and the table is written to ``<out>/scaling.md``. Run::

    PYTHONPATH=. python benchmarks/bench_scaling.py --sizes 10,100 --modes plain,batched,cluster
    PYTHONPATH=. python benchmarks/bench_scaling.py --report-only
"""

from __future__ import annotations

import argparse
import json
import lzma
import os
import pickle
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

FOLLOWERS_PER_PLATOON = 10
MAX_GENERATED = 1000
MODES = ("plain", "devices", "batched", "cluster")
# smc's default moves; rows without this field had the random walk with the pass along the data,
# rows marked "paired" the paired independent + random-walk moves (defaults between e1d9eb0 and
# 0b67778), "random walk" the random walk alone (until 02768b0). Rows record the commit they ran
# at: the likelihood got about 5x cheaper at c4a39fe.
SMC_MOVES = "random walk, paired closing moves"


def commit() -> str:
    """The library's commit, marked dirty when the work tree differs from it."""

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", *args], cwd=ROOT, capture_output=True, text=True, check=False
        ).stdout.strip()

    return git("rev-parse", "--short", "HEAD") + ("-dirty" if git("status", "--porcelain") else "")


def machine() -> str:
    """The JAX device kind and the CPU count: rows of different machines are kept apart."""
    import jax

    device = jax.devices()[0]
    kind = device.device_kind if device.platform != "cpu" else "cpu"
    return f"{kind} ({os.cpu_count()} cores)"


def followers(size: int, duration_s: float, seed: int, workdir: Path):
    """The first ``size`` followers (whole series) of a generated recording with enough platoons;
    beyond :data:`MAX_GENERATED`, copies of those under new ids (``<id>#<copy>``): each id is its
    own random stream, and fitting costs the same whether the data repeat or not, while
    generating and reading 10,000 followers would take longer than fitting them."""
    from bayesdrive.data.readers import read
    from bayesdrive.data.views import follower_arrays
    from trafficgen import generate

    generated = min(size, MAX_GENERATED)
    platoons = -(-generated // FOLLOWERS_PER_PLATOON)
    path = workdir / f"platoons_{platoons}_{duration_s:g}s_{seed}.csv"
    # Reading and checking 1,000 generated followers takes about a minute, longer than fitting
    # them on a GPU: the read arrays are kept beside the recording for the next process.
    read_arrays = path.with_suffix(".followers.pickle.xz")
    if read_arrays.exists():
        arrays = pickle.loads(lzma.decompress(read_arrays.read_bytes()))
    else:
        if not path.exists():
            generate(
                seed,
                path,
                None,
                platoons=platoons,
                followers=FOLLOWERS_PER_PLATOON,
                duration_s=duration_s,
                cut_ins=0,
            )
        arrays = follower_arrays(read(path, format="ngsim_raw"), window="all")
        read_arrays.write_bytes(lzma.compress(pickle.dumps(arrays), preset=3))
    if len(arrays.vehicle_ids) < generated:
        raise RuntimeError(f"the recording holds {len(arrays.vehicle_ids)} followers, not {size}")
    arrays = arrays.subset(slice(0, generated))
    copies = -(-size // generated)
    if copies == 1:
        return arrays
    tiled = arrays.subset(np.tile(np.arange(generated), copies)[:size])
    ids = [f"{v}#{i // generated}" for i, v in enumerate(tiled.vehicle_ids)]
    return tiled._replace(vehicle_ids=tuple(ids))


def ngsim_followers(size: int):
    """The first ``size`` NGSIM I-80 chain followers with usable steps in their fitting windows
    (0: all of them)."""
    from bayesdrive.data import registry
    from bayesdrive.data.views import follower_arrays

    arrays = follower_arrays(registry.load("ngsim_i80_chains"), window="fit")
    return arrays if size == 0 else arrays.subset(slice(0, size))


def run_one(mode: str, size: int, args: argparse.Namespace) -> dict:
    """Fit ``size`` followers in ``mode``; times, memory and the step count. With ``--means``,
    each vehicle's posterior means and sds go to ``<out>/means-<source>-<mode>-<size>.json``."""
    import jax

    from bayesdrive.drivers.idm import IDM
    from bayesdrive.inference.engines import smc

    if args.source == "trafficgen":
        arrays = followers(size, args.duration, args.seed, Path(args.workdir))
    else:
        arrays = ngsim_followers(size)
        size = len(arrays.vehicle_ids)
    steps = int(np.asarray(arrays.mask).sum())
    key = jax.random.key(args.seed)
    row = {
        "source": args.source,
        "mode": mode,
        "vehicles": size,
        "steps": steps,
        "particles": args.particles,
    }
    started = time.perf_counter()
    if mode == "cluster":
        from bayesdrive.inference.distributed import fit_on_cluster, open_cluster

        with tempfile.TemporaryDirectory() as folder, open_cluster("local:2") as client:
            opened = time.perf_counter()
            fit_on_cluster(
                client,
                key,
                arrays,
                folder=Path(folder),
                model=IDM,
                engine="smc",
                window="all",
                num_particles=args.particles,
            )
            row["inference_s"] = time.perf_counter() - opened
            row["cluster_start_s"] = opened - started
            workers = client.run(lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
            row["worker_peak_mib"] = max(workers.values())
        row["compile_s"] = None  # inside every worker's first chunk
    else:
        batch = args.batch if mode == "batched" else 1
        result = smc.run(
            key,
            arrays,
            model=IDM,
            num_particles=args.particles,
            vehicle_batch=batch,
        )
        row["inference_s"] = result.wall_time_s
        row["compile_s"] = result.compile_time_s
        row["batch"] = batch
        row["devices"] = jax.local_device_count()
        if args.means:
            summary = {
                name: {
                    "mean": draws.mean(axis=(0, 1)).tolist(),
                    "sd": draws.std(axis=(0, 1)).tolist(),
                }
                for name, draws in result.posterior.items()
            }
            summary["vehicle_ids"] = list(arrays.vehicle_ids)
            target = Path(args.out) / f"means-{args.source}-{mode}-{size}.json"
            target.write_text(json.dumps(summary))
    row["whole_s"] = time.perf_counter() - started
    row["peak_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    row["per_vehicle_s"] = row["inference_s"] / size
    row["machine"] = machine()
    row["smc_moves"] = SMC_MOVES
    row["jax"] = jax.__version__
    row["python"] = platform.python_version()
    return row


def load_rows(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def write_report(out: Path) -> str:
    """The markdown table of every row, by machine, mode and size."""
    from bayesdrive.data.atomic import write_text_atomic

    rows = sorted(
        load_rows(out / "runs.jsonl"),
        key=lambda r: (
            r["machine"],
            r.get("source", "trafficgen"),
            r.get("smc_moves", "random walk"),
            r.get("commit", ""),
            MODES.index(r["mode"]),
            r["vehicles"],
        ),
    )
    lines = [
        "| machine | data | smc moves | commit | mode | vehicles | steps | inference (s) "
        "| per vehicle (s) | compile (s) | whole (s) | peak memory (MiB) | worker peak (MiB) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        mode = r["mode"] + (f" (batch {r['batch']})" if r.get("batch", 1) > 1 else "")
        if r.get("devices", 1) > 1:
            mode += f" ({r['devices']} devices)"
        compile_s = "in workers" if r["compile_s"] is None else f"{r['compile_s']:.1f}"
        worker = f"{r['worker_peak_mib']:.0f}" if "worker_peak_mib" in r else ""
        lines.append(
            f"| {r['machine']} | {r.get('source', 'trafficgen')} | {r.get('smc_moves', 'random walk')} "
            f"| {r.get('commit', '')} | {mode} | {r['vehicles']} | {r['steps']} | {r['inference_s']:.1f} "
            f"| {r['per_vehicle_s']:.3f} | {compile_s} | {r['whole_s']:.1f} | {r['peak_mib']:.0f} "
            f"| {worker} |"
        )
    text = (
        "# smc scaling with the number of vehicles\n\n"
        "Generated by `benchmarks/bench_scaling.py` from `runs.jsonl` (module docstring: "
        "protocol). Followers from `trafficgen`, whole series, smc defaults, six IDM parameters; "
        "each row one fresh process.\n\n" + "\n".join(lines) + "\n"
    )
    write_text_atomic(out / "scaling.md", text)
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="10,100")
    parser.add_argument("--modes", default=",".join(MODES))
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--particles", type=int, default=1000)
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--seed", type=int, default=20261124)
    parser.add_argument("--out", type=Path, default=ROOT / "reports" / "scaling")
    parser.add_argument("--workdir", default=None, help="where generated recordings are kept")
    parser.add_argument(
        "--source",
        choices=("trafficgen", "ngsim_i80_chains"),
        default="trafficgen",
        help="generated followers, or NGSIM I-80 chain followers' fitting windows (size 0: all)",
    )
    parser.add_argument("--means", action="store_true", help="save posterior means and sds")
    parser.add_argument("--report-only", action="store_true")
    parser.add_argument("--one", nargs=2, metavar=("MODE", "SIZE"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        print(json.dumps(run_one(args.one[0], int(args.one[1]), args)))
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    if args.report_only:
        print(write_report(args.out))
        return 0
    modes = args.modes.split(",")
    unknown = sorted(set(modes) - set(MODES))
    if unknown:
        parser.error(f"unknown mode(s) {unknown}; known: {list(MODES)}")
    here = machine()
    done = {
        (r["machine"], r.get("source", "trafficgen"), r.get("commit"), r["mode"], r["vehicles"])
        for r in load_rows(args.out / "runs.jsonl")
    }
    version = commit()
    with tempfile.TemporaryDirectory() as scratch:
        workdir = args.workdir or scratch
        for size in sorted(int(s) for s in args.sizes.split(",")):
            for mode in modes:
                if (here, args.source, version, mode, size) in done:
                    continue
                command = [
                    sys.executable,
                    __file__,
                    "--one",
                    mode,
                    str(size),
                    "--workdir",
                    workdir,
                    "--batch",
                    str(args.batch),
                    "--particles",
                    str(args.particles),
                    "--duration",
                    str(args.duration),
                    "--seed",
                    str(args.seed),
                    "--source",
                    args.source,
                    "--out",
                    str(args.out),
                    *(["--means"] if args.means else []),
                ]
                env = dict(os.environ)
                if mode == "devices":
                    cores = len(os.sched_getaffinity(0))
                    env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={cores}"
                finished = subprocess.run(
                    command, capture_output=True, text=True, check=False, env=env
                )
                if finished.returncode != 0:
                    print(finished.stderr[-3000:], file=sys.stderr)
                    return finished.returncode
                row = json.loads(finished.stdout.strip().splitlines()[-1])
                row["commit"] = version  # before this run's own rows made the tree dirty
                with open(args.out / "runs.jsonl", "a") as handle:
                    handle.write(json.dumps(row) + "\n")
                print(f"{mode:8s} {size:6d} vehicles: {row['inference_s']:.1f} s", flush=True)
    print(write_report(args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
