"""What every engine does around its own per-vehicle kernel, written once.

Every engine is ``run(key, arrays, *, <its own options>, **inputs)``, ``inputs`` the keyword
arguments all engines share (:class:`~bayesdrive.inference.core.output.EngineInputs`, described there
once). :func:`prepare` is every engine's preamble: take those inputs (with the engine's default
size), refuse a model the engine cannot fit, check the inferred and fixed parameters, take the
prior (the model's uniform box by default) and build every step's inputs through the model
(:func:`~bayesdrive.inference.core.likelihood.step_inputs`). It returns a :class:`VehicleProblem`, which runs a kernel over all vehicles
(:meth:`VehicleProblem.run`, through :func:`map_vehicles`) and scores draws; :func:`posterior_draws`
and :func:`log_likelihood_draws` put per-vehicle outputs in the result's (chain, draw, vehicle)
layout (:func:`one_chain_result` the whole result of an engine with one chain per vehicle). An
engine keeps only its kernel, its own options and its own sample stats.

**Per-vehicle keys.** A vehicle's PRNG key is the run's key with the vehicle's id folded in
(:func:`vehicle_keys`: ``fold_in`` of a stable 64-bit hash of the UTF-8 id, as two 32-bit
words), and replicate ``r`` of a vehicle folds in ``r`` as well. Every random draw of a vehicle comes from its
own key, and chunks of vehicles are fixed by the data order and the chunk size, so a vehicle's
draws are bit-identical whether it is fitted alone, with others, in another order or in another
chunk. 64 bits, not 32: among 100,000 vehicles (a HighD-sized data set) two 32-bit hashes would
likely coincide and give two vehicles one random stream.
"""

from __future__ import annotations

import functools
import hashlib
import time
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, NamedTuple

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import DriverModel
from bayesdrive.inference.core.likelihood import (
    StepInputs,
    check_model,
    fixed_params,
    param_names,
    score_draws,
    step_inputs,
)
from bayesdrive.inference.core.output import EngineInputs, EngineResult

__all__ = [
    "VehicleProblem",
    "clear_compiled",
    "log_likelihood_draws",
    "map_vehicles",
    "one_chain_result",
    "posterior_draws",
    "prepare",
    "static_key",
    "vehicle_hash",
    "vehicle_keys",
]


def vehicle_hash(vehicle_id: str) -> tuple[int, int]:
    """The first 8 bytes of the sha256 of the UTF-8 id, as two unsigned 32-bit words."""
    digest = hashlib.sha256(vehicle_id.encode("utf-8")).digest()
    return int.from_bytes(digest[:4], "big"), int.from_bytes(digest[4:8], "big")


def vehicle_keys(key: Array, vehicle_ids: Sequence[str], replicates: int | None = None) -> Array:
    """One key per vehicle, (vehicle,), from ``key`` and each id (module docstring); with
    ``replicates``, one per replicate and vehicle, (replicate, vehicle), the index folded in too."""
    words = np.array([vehicle_hash(v) for v in vehicle_ids], dtype=np.uint32).reshape(-1, 2)

    def one(high, low):
        return jax.random.fold_in(jax.random.fold_in(key, high), low)

    keys = jax.vmap(one)(jnp.asarray(words[:, 0]), jnp.asarray(words[:, 1]))
    if replicates is None:
        return keys
    indices = jnp.arange(replicates, dtype=jnp.uint32)
    return jax.vmap(lambda r: jax.vmap(lambda k: jax.random.fold_in(k, r))(keys))(indices)


class VehicleProblem(NamedTuple):
    """One engine's view of a fit: the model, the inferred ``names`` (in order), the full
    parameter tuple ``fixed`` (defaults where not given), the model's uniform ``box`` over
    ``names``, the ``prior`` (the box unless one was given), every vehicle's ``series``
    (vehicle, step), the ``vehicle_ids``, the run's size ``num_particles``, the ``progress``
    callback and whether the result keeps the ``pointwise`` log-likelihood
    (:class:`~bayesdrive.inference.core.output.EngineInputs`)."""

    model: DriverModel
    names: tuple[str, ...]
    fixed: Any
    box: Any
    prior: Any
    series: StepInputs
    vehicle_ids: tuple[str, ...]
    num_particles: int
    progress: Callable[[int, int], None] | None
    pointwise: bool

    @property
    def num_vehicles(self) -> int:
        return len(self.vehicle_ids)

    @property
    def given_prior(self) -> Any:
        """The prior the caller gave, None for the model's box."""
        return None if self.prior is self.box else self.prior

    def keys(self, key: Array) -> Array:
        """Every vehicle's key (:func:`vehicle_keys`), (vehicle,)."""
        return vehicle_keys(key, self.vehicle_ids)

    def cache_key(self, *settings: Any) -> Any:
        """A key for :func:`map_vehicles`'s compile cache: the model, names and fixed values plus
        ``settings`` (hashable; None where one is not, which turns caching off)."""
        parts = (self.model, self.names, static_key(self.fixed), *settings)
        return None if any(part is None for part in parts) else parts

    def run(
        self,
        kernel: Callable[..., Any],
        key: Array,
        *,
        settings: tuple[Any, ...],
        replicates: int = 1,
        chunk: int,
        batch: int | None,
        progress: Callable[[int, int], None] | None = None,
        **options: Any,
    ) -> tuple[Any, float, float]:
        """``kernel(key, series, model=, names=, fixed=, **options)``, this problem's model,
        inferred names and fixed values bound, on every vehicle, ``replicates`` times with
        independent keys.

        ``settings`` (the engine's name and whatever determines ``options``, hashable) key the
        compiled program with the model, names and fixed values (:meth:`cache_key`). Outputs are
        numpy arrays with leading axes (replicate, vehicle); the compile and run times as
        :func:`map_vehicles` gives them. Replicates run as extra vehicles, replicate-major
        (``progress`` counts them as vehicles).
        """
        per_vehicle = functools.partial(
            kernel, model=self.model, names=self.names, fixed=self.fixed, **options
        )
        keys = vehicle_keys(key, self.vehicle_ids, replicates)
        keys = keys.reshape(-1, *keys.shape[2:])  # raw uint32 keys keep their trailing axis
        # Repeat along the vehicle axis only (merge scenes carry a trailing merge-slot axis).
        copies = jax.tree.map(lambda a: jnp.concatenate([a] * replicates), self.series)
        out, compile_time, run_time = map_vehicles(
            per_vehicle,
            (keys, copies),
            chunk=chunk,
            batch=batch,
            progress=progress,
            cache_key=self.cache_key(*settings),
        )
        out = jax.tree.map(lambda a: a.reshape(replicates, self.num_vehicles, *a.shape[1:]), out)
        return out, compile_time, run_time

    def score(self, draws: Array | np.ndarray) -> np.ndarray:
        """Per-step log-likelihood (vehicle, draw, step) of draws (vehicle, draw, d)."""
        return score_draws(self.model, self.names, self.fixed, draws, self.series)

    def pointwise_scores(self, draws: Array | np.ndarray) -> np.ndarray | None:
        """:meth:`score` for the result's log_likelihood group; None (nothing scored) where the
        fit leaves the group out."""
        return self.score(draws) if self.pointwise else None


def _engine_model(engine: str, inputs: EngineInputs) -> DriverModel:
    """The ``model`` of an engine's ``inputs``; a TypeError, as for any keyword-only argument,
    names an input missing or not in :class:`~bayesdrive.inference.core.output.EngineInputs`
    (nothing passed is ignored)."""
    unknown = sorted(set(inputs) - set(EngineInputs.__annotations__))
    if unknown:
        raise TypeError(f"engine {engine!r} got unexpected keyword argument(s) {unknown}")
    if "model" not in inputs:
        raise TypeError(f"engine {engine!r} is missing the keyword argument 'model'")
    return inputs["model"]


def prepare(
    engine: str,
    arrays: FollowerArrays,
    inputs: EngineInputs,
    *,
    num_particles: int,
    whole_series: bool = False,
    check: Callable[[DriverModel], None] | None = None,
) -> VehicleProblem:
    """Every engine's preamble (module docstring) on its ``inputs``
    (:class:`~bayesdrive.inference.core.output.EngineInputs`), ``num_particles`` the engine's default
    size. ``check`` refuses a model the engine cannot fit (default:
    :func:`~bayesdrive.inference.core.likelihood.check_model` for ``engine``, which scores whole series
    when ``whole_series``)."""
    model = _engine_model(engine, inputs)
    prior = inputs.get("prior")
    if check is None:
        check_model(model, engine, whole_series=whole_series)
    else:
        check(model)
    names = param_names(model, inputs.get("params"))
    vehicle_ids = tuple(str(v) for v in arrays.vehicle_ids)
    repeated = sorted(v for v, count in Counter(vehicle_ids).items() if count > 1)
    if repeated:
        raise ValueError(
            f"vehicle ids must be distinct (each names a vehicle's random stream); repeated: "
            f"{repeated[:10]}"
        )
    box = model.prior(names)
    return VehicleProblem(
        model=model,
        names=names,
        fixed=fixed_params(model, inputs.get("fixed")),
        box=box,
        prior=box if prior is None else prior,
        series=step_inputs(arrays, model),
        vehicle_ids=vehicle_ids,
        num_particles=inputs.get("num_particles", num_particles),
        progress=inputs.get("progress"),
        pointwise=inputs.get("pointwise", True),
    )


def posterior_draws(names: Sequence[str], theta: np.ndarray) -> dict[str, np.ndarray]:
    """Draws (vehicle, chain, draw, d) as the result's posterior: name -> (chain, draw, vehicle)."""
    values = np.moveaxis(np.asarray(theta, dtype=np.float64), 0, 2)
    return {name: values[..., i] for i, name in enumerate(names)}


def log_likelihood_draws(values: np.ndarray | None) -> np.ndarray | None:
    """Scores (vehicle, chain, draw, step) in the result's (chain, draw, vehicle, step) layout
    (None, for a fit without the pointwise log-likelihood, stays None)."""
    return None if values is None else np.moveaxis(np.asarray(values), 0, 2)


def one_chain_result(
    names: Sequence[str], draws: np.ndarray, log_likelihood: np.ndarray | None, **fields: Any
) -> EngineResult:
    """The result of an engine whose draws of a vehicle form one chain: ``draws``
    (vehicle, draw, d) and their scores ``log_likelihood`` (vehicle, draw, step; or None) get the
    chain axis; ``fields`` are the other :class:`~bayesdrive.inference.core.output.EngineResult`
    fields."""
    scores = None if log_likelihood is None else np.asarray(log_likelihood)[:, None]
    return EngineResult(
        posterior=posterior_draws(names, np.asarray(draws)[:, None]),
        log_likelihood=log_likelihood_draws(scores),
        **fields,
    )


# Compiled chunk runners by cache key, so repeated fits of one shape (tests, seed studies) compile
# once per process; bounded, because each entry holds an executable, yet large enough for every
# program of a criticism (one per extension and start kind) to stay.
_COMPILED: dict[Any, Any] = {}
_COMPILED_MAX = 64


def clear_compiled() -> None:
    """Forget every cached compiled chunk (the next fit compiles again, e.g. to time it)."""
    _COMPILED.clear()


def map_vehicles(
    per_vehicle: Callable[..., Any],
    inputs: tuple[Any, ...],
    *,
    chunk: int,
    batch: int | None,
    progress: Callable[[int, int], None] | None = None,
    cache_key: Any = None,
) -> tuple[Any, float, float]:
    """Run ``per_vehicle`` on every vehicle, ``chunk`` vehicles per compiled call.

    ``inputs`` are pytrees with a leading vehicle axis; ``per_vehicle`` gets one vehicle's slice.
    Inside a chunk, ``batch`` vehicles are vectorised together (None or 1: one after another, which
    keeps ``lax.cond`` a real branch; under ``vmap`` it becomes a select that runs both sides).
    With several local JAX devices (GPUs, or CPU devices from
    ``XLA_FLAGS=--xla_force_host_platform_device_count=N``) each chunk is split over them along
    the vehicle axis, every device taking whole batches and running the same single-device
    program, compiled once per device, on its share (dispatched asynchronously, so the devices
    work at once). The same program, not a partitioned one: a chunk sharded by ``shard_map``
    compiled into other float operations and changed draws in the last bits with the device
    count. So a vehicle's draws do not depend on the device count. A chunk holds at least one
    batch; fewer vehicles than ``chunk`` make a chunk of the next power of two. A chunk's rows
    past the last vehicle repeat it but are not computed, so the function compiles once, ahead of
    time. ``cache_key`` (hashable, or None for no caching) must determine ``per_vehicle``
    completely: the compiled chunk is reused for the same key and input shapes, and the compile
    time is then 0. Returns the stacked numpy outputs, the compile time and the run time (compile
    excluded) in seconds; ``progress(done, total)`` is called after each chunk.
    """
    num_vehicles = jax.tree.leaves(inputs)[0].shape[0]
    batch_size = None if batch is None or batch <= 1 else min(batch, num_vehicles)
    size = batch_size or 1
    # Every device takes whole batches of a chunk: chunks hold at least one batch and are a
    # multiple of (devices x batch), so vehicles are vectorised in the same consecutive batches
    # whatever the device count.
    devices = jax.local_devices()
    multiple = len(devices) * size
    wanted = max(1, min(chunk, num_vehicles), size)
    if wanted < chunk:
        # Fewer vehicles than a chunk: a power of two, so fits of similar size share one
        # compiled program (in this process and in JAX's persistent cache); rows past the last
        # vehicle cost nothing, as each call runs only the batches that hold vehicles.
        wanted = min(chunk, 1 << (wanted - 1).bit_length())
    chunk = -(-wanted // multiple) * multiple
    per_device = chunk // len(devices)

    def batches_at(start: int) -> list[np.int32]:
        """Each device's count of batches holding vehicles in the chunk starting at ``start``."""
        held = np.clip(num_vehicles - start - per_device * np.arange(len(devices)), 0, per_device)
        return [np.int32(-(-n // size)) for n in held]

    def run_share(count, *share):
        # The trip count is an argument, and every share ends with one batch never computed, so
        # the compiler can neither unroll the loop nor hoist a loop-invariant slice out of it:
        # either fuses the work with its surroundings and changes float bits (a vehicle fitted
        # alone would differ from the same vehicle in a longer chunk).
        def one(i):
            rows = jax.tree.map(lambda a: jax.lax.dynamic_slice_in_dim(a, i * size, size), share)
            if batch_size is None:  # no vmap: lax.cond stays a branch
                alone = per_vehicle(*jax.tree.map(lambda a: a[0], rows))
                return jax.tree.map(lambda a: a[None], alone)
            return jax.vmap(per_vehicle)(*rows)

        # Traced once: the jaxpr gives the output shapes and is replayed in the loop. Shapes from
        # eval_shape and the loop's own trace would trace the kernel twice, the costliest part of
        # building the program after XLA's compile.
        traced, shapes = jax.make_jaxpr(one, return_shape=True)(np.int32(0))
        replay = jax.extend.core.jaxpr_as_fun(traced)
        out_tree = jax.tree.structure(shapes)
        length = jax.tree.leaves(share)[0].shape[0]
        empty = jax.tree.map(lambda s: jnp.zeros((length, *s.shape[1:]), s.dtype), shapes)

        def fill(i, out):
            return jax.tree.map(
                lambda o, part: jax.lax.dynamic_update_slice_in_dim(o, part, i * size, 0),
                out,
                jax.tree.unflatten(out_tree, replay(i)),
            )

        return jax.lax.fori_loop(0, count, fill, empty)

    def shares_at(start: int) -> list[Any]:
        """Each device's rows of the chunk starting at ``start``, with its unused batch, on it."""
        rows = start + np.arange(chunk).reshape(len(devices), per_device)
        rows = np.minimum(np.concatenate([rows, rows[:, -size:]], axis=1), num_vehicles - 1)
        return [
            jax.device_put(jax.tree.map(lambda a, r=r: a[r], inputs), device)
            for r, device in zip(rows, devices, strict=True)
        ]

    first = shares_at(0)
    shapes = jax.tree.map(lambda a: (a.shape, str(a.dtype)), first[0])
    key = None if cache_key is None else (cache_key, chunk, batch_size, len(devices), str(shapes))
    compile_time = 0.0
    if key is None or key not in _COMPILED:
        started = time.perf_counter()
        jitted = jax.jit(run_share)
        lowered = [jitted.lower(np.int32(0), *share) for share in first]
        # XLA compiles outside the GIL: one thread per device keeps the compile time that of one.
        with ThreadPoolExecutor(len(lowered)) as pool:
            compiled = list(pool.map(lambda program: program.compile(), lowered))
        compile_time = time.perf_counter() - started
        if key is not None:
            if len(_COMPILED) >= _COMPILED_MAX:
                _COMPILED.pop(next(iter(_COMPILED)))
            _COMPILED[key] = compiled
    else:
        compiled = _COMPILED[key]

    pieces, run_time = [], 0.0
    for start in range(0, num_vehicles, chunk):
        shares = first if start == 0 else shares_at(start)
        started = time.perf_counter()
        outs = [
            program(count, *share)
            for program, count, share in zip(compiled, batches_at(start), shares, strict=True)
        ]
        outs = jax.block_until_ready(outs)
        run_time += time.perf_counter() - started
        # Each device's outputs without its unused batch, in vehicle order.
        out = jax.tree.map(
            lambda *parts: np.concatenate([np.asarray(p)[:per_device] for p in parts]), *outs
        )
        keep = min(chunk, num_vehicles - start)
        pieces.append(jax.tree.map(lambda a, keep=keep: a[:keep], out))
        if progress is not None:
            progress(start + keep, num_vehicles)
    stacked = jax.tree.map(lambda *parts: np.concatenate(parts), *pieces)
    return stacked, compile_time, run_time


def static_key(value: Any) -> Any:
    """A hashable stand-in for a prior or a parameter tuple, for ``map_vehicles``'s cache key.

    Arrays become tuples of floats; leaves other than arrays, numbers and strings give None (no
    caching), because an object hashed by identity could change between fits.
    """
    leaves, treedef = jax.tree.flatten(value)
    frozen = []
    for leaf in leaves:
        if hasattr(leaf, "shape"):
            frozen.append((np.shape(leaf), tuple(np.asarray(leaf).ravel().tolist())))
        elif isinstance(leaf, str | int | float):
            frozen.append(leaf)
        else:
            return None
    return (type(value).__qualname__, str(treedef), tuple(frozen))
