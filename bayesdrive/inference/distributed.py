"""``fit`` on a Dask cluster: chunks of vehicles as tasks, each chunk's result saved as it finishes.

The criticism's fits (:func:`~bayesdrive.inference.engines.heldout_evidence.fit_model`) run in chunks the
same way (:func:`fit_model_on_cluster`), each vehicle from its own key, so a criticism on a cluster
reports what the plain run reports; its chunks are not saved (a criticism is one result).

Vehicles are split into chunks of ``chunk_size`` in the data's order, never by the number of
workers, and every vehicle's key derives from the run's key and its own id
(:func:`~bayesdrive.inference.core.vehicles.vehicle_keys`), so the combined result is bit-identical to
one :func:`~bayesdrive.inference.fit.fit` of all vehicles, whatever the cluster, the order chunks
finish in, a worker lost mid-run (Dask runs its task again elsewhere) or a restart. Chunks are
sliced from one padded array of all vehicles, so each has the plain run's step axis.

The folder given holds ``chunks/index.json`` (the run's chunks and their vehicle ids) and
``chunks/chunk-NNNN.nc``, each written atomically by the client as its task completes (workers
need no shared file system). A rerun into the same folder skips the chunks whose files are there;
a chunk file that cannot be read is logged and fitted again. When all are done they are combined
into one result tree, the one ``fit`` would have returned. The module knows no CLI; clusters come
from :func:`open_cluster`: ``local`` or ``local:N`` (a ``LocalCluster`` of N process workers,
default one per core, each confined to one core so that XLA runs one thread) or a scheduler
address such as ``tcp://HOST:8786``.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import os
import shutil
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr
from jax import Array

from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.views import FollowerArrays, Window, follower_arrays
from bayesdrive.drivers.base import DriverModel
from bayesdrive.drivers.extensions.compose import ExtendedModel
from bayesdrive.drivers.idm import IDM
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.core.output import (
    load_result,
    metadata,
    psis_loo_check,
    save_result,
    set_metadata,
)
from bayesdrive.inference.core.smc import TemperingConfig
from bayesdrive.inference.diagnostics.convergence import check_convergence, log_problems
from bayesdrive.inference.engines.heldout_evidence import FitResult, fit_model, join_fits
from bayesdrive.inference.fit import MCMC_OPTIONS, first_vehicles, fit

__all__ = [
    "DEFAULT_CHUNK_SIZE",
    "JOINT_ENGINES",
    "chunk_rows",
    "cluster_workers",
    "fit_model_on_cluster",
    "fit_on_cluster",
    "open_cluster",
    "remove_chunks",
    "run_tasks",
]

log = logging.getLogger(__name__)

DEFAULT_CHUNK_SIZE = 16
# Engines that fit vehicles jointly (a population model): their vehicles cannot be split.
JOINT_ENGINES = frozenset({"hierarchical"})
CHUNKS = "chunks"
INDEX = "index.json"


def chunk_rows(num_vehicles: int, chunk_size: int) -> list[range]:
    """The vehicle rows of each chunk: consecutive runs of ``chunk_size`` in data order."""
    if chunk_size < 1:
        raise ValueError(f"the chunk size must be positive, got {chunk_size}")
    return [
        range(start, min(start + chunk_size, num_vehicles))
        for start in range(0, num_vehicles, chunk_size)
    ]


def _cores() -> list[int]:
    return sorted(os.sched_getaffinity(0))


def _one_device_flags() -> str:
    """This process's ``XLA_FLAGS`` with one CPU device: a local worker owns one core."""
    kept = [
        flag
        for flag in os.environ.get("XLA_FLAGS", "").split()
        if not flag.startswith("--xla_force_host_platform_device_count")
    ]
    return " ".join([*kept, "--xla_force_host_platform_device_count=1"])


def _one_core_each(cores: list[int]) -> Any:
    """A worker plugin confining local worker ``name`` to one of ``cores`` as it starts (a
    worker restarted after a crash too), before JAX does, so XLA and every other pool size
    themselves to one thread. Not XLA_FLAGS=--xla_cpu_multi_thread_eigen=false: that flag picks
    other kernels, whose results differ in the last bits from a plain run's."""
    from distributed import WorkerPlugin

    class OneCore(WorkerPlugin):
        name = "bayesdrive-one-core"

        def setup(self, worker: Any) -> None:
            os.sched_setaffinity(0, {cores[int(worker.name) % len(cores)]})

    return OneCore()


def cluster_workers(cluster: str) -> int | None:
    """Check a cluster spec (module docstring) before any work: the worker count of a local
    cluster, None for a scheduler address. A ValueError names a malformed spec or a missing
    ``distributed``."""
    if importlib.util.find_spec("distributed") is None:
        raise ValueError(
            "--cluster needs Dask's distributed scheduler: pip install 'bayesdrive[cluster]'"
        )
    if cluster == "local" or cluster.startswith("local:"):
        count = cluster.partition(":")[2]
        if count and not (count.isdigit() and int(count) > 0):
            raise ValueError(f"--cluster {cluster}: the worker count must be a positive integer")
        return int(count) if count else len(_cores())
    if "://" not in cluster:
        raise ValueError(
            f"--cluster {cluster!r}: give local, local:N or a scheduler address such as "
            "tcp://HOST:8786"
        )
    return None


@contextmanager
def _quiet_scheduler() -> Iterator[None]:
    """A local scheduler runs in this process and logs every worker's comings and goings at
    INFO; only its warnings are worth a user's attention."""
    logger = logging.getLogger("distributed")
    level = logger.level
    logger.setLevel(max(logger.getEffectiveLevel(), logging.WARNING))
    try:
        yield
    finally:
        logger.setLevel(level)


@contextmanager
def open_cluster(cluster: str) -> Iterator[Any]:
    """A ``distributed.Client`` for ``cluster`` (checked as :func:`cluster_workers` does), closed
    (and a local cluster shut down) on leaving."""
    workers = cluster_workers(cluster)
    from distributed import Client, LocalCluster

    if workers is None:
        try:
            client = Client(cluster, timeout="30s")
        except OSError as error:
            raise ValueError(f"--cluster {cluster}: cannot reach the scheduler ({error})") from None
        with client:
            yield client
        return
    with (
        _quiet_scheduler(),
        LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            silence_logs=logging.ERROR,
            env={"XLA_FLAGS": _one_device_flags()},
        ) as local,
        Client(local) as client,
    ):
        client.register_plugin(_one_core_each(_cores()))
        yield client


def _by_name(model: DriverModel) -> DriverModel | str:
    """A registry model's name (each worker then uses its own registry's object), else the model:
    a model's functions unpickled anew for every task would miss the compile cache, so every
    chunk would compile again."""
    try:
        return model.name if get_model(model.name) is model else model
    except KeyError:
        return model


def run_tasks(
    client: Any,
    task: Callable[[Any, Any], Any],
    shared: Any,
    inputs: Mapping[int, Any],
    on_done: Callable[[int, Any], None],
) -> None:
    """``task(shared, inputs[i])`` for every ``i`` on the Dask ``client``; ``shared`` is sent once
    to every worker, which hands every task the same object (a model not in the registry then
    compiles once per worker and run, not once per task). ``on_done(i, result)`` runs in this
    process as each task finishes, in whatever order they finish."""
    from distributed import as_completed

    [sent] = client.scatter([shared], broadcast=True, hash=False)
    futures = {client.submit(task, sent, value, pure=False): i for i, value in inputs.items()}
    for future in as_completed(futures):
        on_done(futures[future], future.result())
        future.release()


def _fit_chunk(options: dict[str, Any], chunk: tuple[Array, FollowerArrays]) -> xr.DataTree:
    """One task: ``fit`` on a chunk's vehicles (runs on a worker)."""
    if isinstance(options["model"], str):
        options = {**options, "model": get_model(options["model"])}
    key, arrays = chunk
    return fit(key, arrays, **options)


def _chunk_path(folder: Path, index: int) -> Path:
    return folder / CHUNKS / f"chunk-{index:04d}.nc"


def _plan(folder: Path, chunks: list[tuple[str, ...]]) -> None:
    """Write the index of chunks, or check that a resumed folder's index is this run's."""
    index = folder / CHUNKS / INDEX
    planned = {"chunks": [list(ids) for ids in chunks]}
    if index.is_file():
        recorded = json.loads(index.read_text(encoding="utf-8"))
        if recorded != planned:
            raise ValueError(
                f"{index}: the interrupted run split other vehicles into chunks (the data changed "
                "since?); use --force to start again"
            )
        return
    write_text_atomic(index, json.dumps(planned, indent=1) + "\n")


def _finished(path: Path, ids: tuple[str, ...]) -> bool:
    """Whether ``path`` holds the fitted chunk of ``ids`` (an unreadable one is logged)."""
    if not path.is_file():
        return False
    try:
        tree = load_result(path)
    except (OSError, ValueError) as error:
        log.warning("%s cannot be read (%s); fitting its vehicles again", path, error)
        return False
    found = tuple(str(v) for v in tree["posterior"]["vehicle"].values)
    if found != ids:
        log.warning("%s holds vehicles %s, not %s; fitting them again", path, found, ids)
        return False
    return True


def _combine(trees: Sequence[xr.DataTree]) -> xr.DataTree:
    """The chunks' trees as one: vehicle-indexed groups joined on ``vehicle``, the
    log-likelihood on ``obs`` (renumbered); anything without those axes must agree."""
    groups = {}
    for name in trees[0].children:
        parts = [tree[name].to_dataset() for tree in trees]
        dim = "obs" if name == "log_likelihood" else "vehicle"
        joined = xr.concat(parts, dim=dim, data_vars="minimal", coords="minimal", compat="equals")
        if dim == "obs":
            joined = joined.assign_coords(obs=np.arange(joined.sizes["obs"]))
        groups[name] = joined
    tree = xr.DataTree.from_dict(groups)
    # netCDF gives numbers back as numpy scalars; metadata is kept in Python's own types.
    tree.attrs = {
        name: value.item() if isinstance(value, np.generic) else value
        for name, value in trees[0].attrs.items()
    }
    return tree


def fit_on_cluster(
    client: Any,
    key: Array,
    data: Trajectories | FollowerArrays,
    *,
    folder: Path,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    model: DriverModel = IDM,
    engine: str = "smc",
    window: Window = "fit",
    max_vehicles: int | None = None,
    vehicle_ids: Sequence[str] | None = None,
    source: str = "FollowerArrays",
    progress: Callable[[int, int], None] | None = None,
    **options: Any,
) -> xr.DataTree:
    """:func:`~bayesdrive.inference.fit.fit` of ``data`` in chunks on the Dask ``client``
    (module docstring); ``folder`` keeps the chunks. ``options`` are ``fit``'s other keyword
    arguments (``vehicle_ids`` picks vehicles of read data only). ``progress(done, total)``
    counts vehicles, chunks already in ``folder`` included."""
    if engine in JOINT_ENGINES:
        raise ValueError(f"engine {engine} fits all vehicles jointly; it cannot run in chunks")
    if isinstance(data, Trajectories):
        picked = None if vehicle_ids is None else list(vehicle_ids)
        arrays = follower_arrays(data, window=window, vehicle_ids=picked)
        source = data.source
        # What fit records of read data, which chunks of arrays cannot know.
        described = {
            "data_format": data.format,
            "flagged_samples": len(data.flags),
            "input_sha256": dict(data.inputs),
            "input_repairs": data.repairs,
        }
    elif vehicle_ids is not None:
        raise ValueError("vehicle_ids picks vehicles of read data; subset the arrays instead")
    else:
        arrays, described = data, {}
    if max_vehicles is not None:
        arrays = first_vehicles(arrays, max_vehicles)
    rows = chunk_rows(len(arrays.vehicle_ids), chunk_size)
    chunks = [tuple(str(arrays.vehicle_ids[i]) for i in r) for r in rows]
    _plan(folder, chunks)

    total, done = len(arrays.vehicle_ids), 0
    todo = []
    for index, ids in enumerate(chunks):
        if _finished(_chunk_path(folder, index), ids):
            done += len(ids)
        else:
            todo.append(index)
    if progress is not None:
        progress(done, total)
    if todo:
        log.info("fitting %d of %d chunk(s) on the cluster", len(todo), len(chunks))

    def save(index: int, tree: xr.DataTree) -> None:
        nonlocal done
        save_result(tree, _chunk_path(folder, index))
        done += len(chunks[index])
        if progress is not None:
            progress(done, total)

    shared = {
        **options,
        "model": _by_name(model),
        "engine": engine,
        "window": window,
        "source": source,
    }
    run_tasks(
        client,
        _fit_chunk,
        shared,
        {index: (key, arrays.subset(np.asarray(rows[index]))) for index in todo},
        save,
    )

    trees = [load_result(_chunk_path(folder, index)) for index in range(len(chunks))]
    tree = _combine(trees)
    parts = [metadata(t) for t in trees]
    set_metadata(
        tree,
        **described,
        max_vehicles=max_vehicles,
        num_vehicles=total,
        usable_steps=int(np.asarray(arrays.mask).sum()),
        compile_time_s=sum(p["compile_time_s"] for p in parts),
        wall_time_s=sum(p["wall_time_s"] for p in parts),
        created_at=datetime.now(UTC).isoformat(timespec="seconds"),
        # Checked on the whole: each chunk's verdict saw its own vehicles only.
        psis_loo=psis_loo_check(tree, markov_chains=engine in MCMC_OPTIONS),
    )
    report = check_convergence(tree)
    log_problems(report)
    set_metadata(tree, convergence=report.as_metadata())
    return tree


def _fit_model_chunk(
    options: dict[str, Any], chunk: tuple[Array, FollowerArrays, FitResult | None]
) -> FitResult:
    """One task: ``fit_model`` on a chunk's vehicles (runs on a worker)."""
    key, series, start = chunk
    return fit_model(key, series, options["extended"], config=options["config"], start=start)


def fit_model_on_cluster(
    client: Any,
    key: Array,
    series: FollowerArrays,
    extended: ExtendedModel,
    *,
    config: TemperingConfig,
    start: FitResult | None = None,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> FitResult:
    """:func:`~bayesdrive.inference.engines.heldout_evidence.fit_model` (one vehicle at a time) of
    ``series`` in chunks of ``chunk_size`` vehicles on the Dask ``client``: the same result, bit
    for bit."""
    rows = chunk_rows(len(series.vehicle_ids), chunk_size)
    parts: dict[int, FitResult] = {}
    run_tasks(
        client,
        _fit_model_chunk,
        {"extended": extended, "config": config},
        {
            index: (key, series.subset(r), None if start is None else start.take(r))
            for index, r in enumerate(rows)
        },
        parts.__setitem__,
    )
    # The workers' copies of the model came back with their fits; the caller's is the model.
    return join_fits([parts[index] for index in range(len(rows))])._replace(model=extended)


def remove_chunks(folder: Path) -> None:
    """Remove the chunk files once the combined result is written beside them."""
    shutil.rmtree(folder / CHUNKS, ignore_errors=True)
