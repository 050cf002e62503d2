r"""``pf``: the paper's particle filter (Bhattacharyya et al., Algorithm 1), done as described.

Per vehicle, a set of N particles over the chosen parameters, every particle on a grid: each
parameter has a documented step (its spec's ``grid_step``: the paper used 0.5 m/s for the IDM's
v_des and 0.1 for sigma) and the grid holds the multiples of the step inside the parameter's prior bounds. At
every usable step t:

1. weight every particle by the exact one-step density of the observed transition
   (``model.transition_logpdf``, in log space),
2. resample N particles (systematic) from those weights,
3. dither: move each parameter of each resampled particle by -1, 0 or +1 grid steps, chosen
   uniformly and independently, clipped to the grid.

Masked steps (padding, flagged samples, outside the window) change nothing. Epochs: the final
particles of all vehicles are pooled, and each vehicle's next epoch starts from N draws of that
pool (epoch 0 starts from the prior, snapped to the grid). The per-vehicle result is its particle
set after the last epoch.

Where the paper's own code differs, this does what the paper describes: that code dithered
particles picked by the weights *before* resampling (so the dithered set was not the resampled
one), and it scored each particle around a noisily simulated next state instead of with the exact
transition density; both are fixed here. The reported ``log_evidence`` (sum over steps of the log
mean weight) is what the paper's filter would report, but it is not a valid evidence: dithering
is an artificial parameter random walk, so the filter targets no fixed-parameter posterior. Use
``smc`` for inference; this engine exists to reproduce the paper honestly.

Each step is the SMC core's step (:func:`bayesdrive.inference.core.smc.step`): the one-step
density as the potential, resampling at every step, the dither as the move. Vectorised over
vehicles (``vmap``) and particles, with a ``lax.scan`` over steps; vehicles are
sorted by series length into chunks and steps where a whole chunk has no data are skipped. Every
random draw of a vehicle (its prior draws, its filter, its start in the next epoch) comes from its
own key, the seed with its id folded in (:mod:`bayesdrive.inference.core.vehicles`), and a vehicle's
filter reads its chunk mates only to decide whether a step computes the model's censored-step
terms (computed for the whole chunk where any vehicle has a censored step; a step without one
scores the same either way): with one epoch its draws are bit-identical whichever vehicles it is
fitted with, in whatever order or chunk. Later epochs start from the pool of all vehicles'
particles, so they depend on the others by design.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple, Unpack

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import DriverModel
from bayesdrive.inference.core.likelihood import StepInputs, censoring, particles_loglik
from bayesdrive.inference.core.output import EngineInputs, EngineResult
from bayesdrive.inference.core.resampling import count_distinct_sorted
from bayesdrive.inference.core.smc import SMCState
from bayesdrive.inference.core.smc import step as smc_step
from bayesdrive.inference.core.vehicles import (
    map_vehicles,
    one_chain_result,
    posterior_draws,
    prepare,
    static_key,
)
from bayesdrive.inference.core.weights import convergence_curve

__all__ = [
    "ACCELERATOR_VEHICLE_CHUNK",
    "CPU_VEHICLE_CHUNK",
    "MAX_DITHERED",
    "Grid",
    "dither_steps",
    "make_grid",
    "run",
]

# One 32-bit word holds this many base-3 dithering digits (3^20 < 2^32).
MAX_DITHERED = 20
# Vehicles vectorised per chunk. On a CPU a small chunk keeps a step's particles in cache and
# computes few padded steps (a chunk runs to its longest series); a power of two, as other sizes
# vectorise worse. An accelerator needs wide chunks to fill it.
CPU_VEHICLE_CHUNK = 8
ACCELERATOR_VEHICLE_CHUNK = 64


class Grid(NamedTuple):
    """Per-parameter grids: value = first + index * step, index in [0, size)."""

    names: tuple[str, ...]
    first: np.ndarray
    step: np.ndarray
    size: np.ndarray

    def values(self, index) -> np.ndarray:
        """Parameter values (float64) of grid indices (..., d)."""
        return self.first + np.asarray(index) * self.step

    def indices(self, values) -> np.ndarray:
        """The nearest grid indices (int32) of parameter values (..., d), in the values'
        precision (as JAX would round them), clipped to the grid."""
        values = np.asarray(values)
        first, step = self.first.astype(values.dtype), self.step.astype(values.dtype)
        last = (self.size - 1).astype(values.dtype)
        return np.clip(np.round((values - first) / step), 0, last).astype(np.int32)


def make_grid(
    model: DriverModel, names: Sequence[str], steps: Mapping[str, float] | None = None
) -> Grid:
    """The multiples of each parameter's step inside its prior bounds (``steps`` overrides the
    specs' ``grid_step``)."""
    declared = {s.name: s.grid_step for s in model.specs if s.grid_step is not None}
    steps = {**declared, **(steps or {})}
    missing = [n for n in names if n not in steps]
    if missing:
        raise ValueError(f"no grid step for parameter(s) {missing}: pass grid_steps={{name: step}}")
    first, step, size = [], [], []
    for name in names:
        spec, h = model.spec(name), float(steps[name])
        if not h > 0:
            raise ValueError(f"grid step of {name!r} must be positive, got {h}")
        # Tolerances absorb float error in bounds that are exact multiples of the step.
        lo = math.ceil(spec.lower / h - 1e-9) * h
        count = math.floor((spec.upper - lo) / h + 1e-9) + 1
        if count < 2:
            raise ValueError(f"grid step {h} of {name!r} leaves fewer than 2 points in its bounds")
        first.append(lo)
        step.append(h)
        size.append(count)
    return Grid(tuple(names), np.array(first), np.array(step), np.array(size, dtype=np.int32))


def dither_steps(key: Array, shape: tuple[int, int]) -> Array:
    """Independent uniform steps in {-1, 0, +1} for (N, d) grid indices.

    One random 32-bit word per particle gives its d steps as base-3 digits: random bits are the
    costly part on a CPU, and d draws per particle made dithering far slower than this. The digits
    are uniform up to 3^d / 2^32 (under 2e-7 for six parameters).
    """
    num, dims = shape
    word = jax.random.bits(key, (num,), dtype=jnp.uint32)
    # Digit k is (word // 3^k) % 3, peeled off one division by the constant 3 at a time: a
    # division by one constant compiles to a multiply and a shift, by a vector of powers it does not.
    three = jnp.uint32(3)
    digits = []
    for _ in range(dims):
        quotient = word // three
        digits.append(word - quotient * three)
        word = quotient
    return jnp.stack(digits, axis=-1).astype(jnp.int32) - 1


class _ChunkOutput(NamedTuple):
    index: Array  # (C, N, d) final grid indices
    log_evidence: Array  # (C,) sum of log mean weights (not a valid evidence: module docstring)
    ess: Array  # (C, T) of the weights before resampling
    unique: Array  # (C, T) distinct ancestors surviving resampling, NaN on masked steps
    mean: Array  # (C, T, d) particle mean after the step
    convergence: Array  # (C, T)


def _pf_chunk(
    keys: Array,
    series: StepInputs,
    start: Array,
    *,
    model: DriverModel,
    names: tuple[str, ...],
    fixed: Any,
    grid: Grid,
    width: Array,
) -> _ChunkOutput:
    """Algorithm 1 on a chunk of C vehicles: (C,) keys, (C, T) series, (C, N, d) start indices.

    Vehicles are vectorised; the scan over steps skips (``lax.cond`` on the whole chunk, so a
    real branch) every step where none of them has data, which with vehicles sorted by length
    removes most of the padding.
    """
    first = jnp.asarray(grid.first, dtype=float)
    step_size = jnp.asarray(grid.step, dtype=float)
    last = jnp.asarray(grid.size - 1)
    num_particles = start.shape[1]

    def dither(key, index):
        return jnp.clip(index + dither_steps(key, index.shape), 0, last), None

    def vehicle_step(index, inputs, key, censored):
        """The SMC core's step: reweight by the step's density, resample every time, dither."""

        def potential(index):
            values = first + index * step_size
            return particles_loglik(model, names, fixed, values, inputs, censored)

        state = SMCState(index, jnp.zeros(num_particles, first.dtype))
        moved, info = smc_step(key, state, potential, dither, resample_below=float("inf"))
        live = inputs.mask > 0
        index = jnp.where(live, moved.particles, index)
        # A step without data reports what the chunk's idle step does, bit for bit, so a
        # vehicle's output does not depend on its chunk mates.
        out = (
            jnp.where(live, info.ess, float(num_particles)),
            jnp.where(live, info.log_increment, 0.0),
            jnp.where(live, count_distinct_sorted(info.ancestors), jnp.nan),
            jnp.mean(first + index * step_size, axis=0),
        )
        return index, out

    def idle_step(index):
        """What a step without data gives: particles kept, equal weights, no resampling."""
        chunk = index.shape[0]
        return index, (
            jnp.full(chunk, float(num_particles)),
            jnp.zeros(chunk),
            jnp.full(chunk, jnp.nan),
            jnp.mean(first + index * step_size, axis=1),
        )

    def step(index, xs):
        inputs, step_keys = xs
        # Whether any vehicle of the chunk has a censored usable step here, decided once for the
        # chunk: not batched, the model's class probabilities are a real branch, skipped on nearly
        # every step (a step that is not censored scores the same either way).
        censored = censoring(model, inputs, usable_only=True)
        return jax.lax.cond(
            jnp.any(inputs.mask > 0),
            lambda: jax.vmap(vehicle_step, in_axes=(0, 0, 0, None))(
                index, inputs, step_keys, censored
            ),
            lambda: idle_step(index),
        )

    num_steps = series.mask.shape[1]
    step_keys = jax.vmap(lambda k: jax.random.split(k, num_steps))(keys)
    time_major = jax.tree.map(lambda a: jnp.swapaxes(a, 0, 1), (series, step_keys))
    index, (ess, log_mean, unique, means) = jax.lax.scan(step, start, time_major)
    ess, log_mean, unique, means = (jnp.swapaxes(a, 0, 1) for a in (ess, log_mean, unique, means))
    return _ChunkOutput(
        index=index,
        log_evidence=jnp.sum(log_mean, axis=1),
        ess=ess,
        unique=unique,
        mean=means,
        convergence=jax.vmap(convergence_curve, in_axes=(0, None))(means, width),
    )


def run(
    key: Array,
    arrays: FollowerArrays,
    *,
    epochs: int = 1,
    grid_steps: Mapping[str, float] | None = None,
    vehicle_chunk: int | None = None,
    **inputs: Unpack[EngineInputs],
) -> EngineResult:
    """The paper's filter (module docstring) over every vehicle of ``arrays``.

    Vehicles are sorted by the length of their series and run ``vehicle_chunk`` at a time,
    vectorised (by default :data:`CPU_VEHICLE_CHUNK` on a CPU, :data:`ACCELERATOR_VEHICLE_CHUNK`
    elsewhere); steps where no vehicle of a chunk has data are skipped. Every vehicle keeps its
    own random stream (module docstring), so with one epoch its results do not depend on the
    other vehicles, their order or the chunk size. ``prior``
    (default the model's uniform box) gives epoch 0's particles, snapped to the grid; those draws,
    before snapping, are the result's ``prior`` group.
    """
    problem = prepare("pf", arrays, inputs, num_particles=1000)
    model, names, num_particles = problem.model, problem.names, problem.num_particles
    if num_particles < 2 or epochs < 1:
        raise ValueError(f"need num_particles >= 2 and epochs >= 1, got {num_particles}, {epochs}")
    if len(names) > MAX_DITHERED:
        raise ValueError(f"pf dithers at most {MAX_DITHERED} parameters, got {len(names)}")
    grid = make_grid(model, names, grid_steps)
    per_chunk = functools.partial(
        _pf_chunk,
        model=model,
        names=names,
        fixed=problem.fixed,
        grid=grid,
        width=problem.box.upper - problem.box.lower,
    )
    cache_key = problem.cache_key("pf", static_key(tuple(grid)))
    series = problem.series
    num_vehicles = problem.num_vehicles
    if vehicle_chunk is None:
        on_cpu = jax.default_backend() == "cpu"
        vehicle_chunk = CPU_VEHICLE_CHUNK if on_cpu else ACCELERATOR_VEHICLE_CHUNK
    # Longest series first, then data-free copies of the shortest to fill the last chunk.
    chunk = max(1, min(vehicle_chunk, num_vehicles))
    live = np.asarray(arrays.mask) > 0
    length = np.where(live.any(axis=1), live.shape[1] - np.argmax(live[:, ::-1], axis=1), 0)
    by_length = np.argsort(-length, kind="stable")
    order = np.concatenate([by_length, np.full(-num_vehicles % chunk, by_length[-1])])
    # Reordered on the host: a JAX op per array would compile a program for each.
    ordered = jax.tree.map(lambda a: np.asarray(a)[order], series)
    ordered.mask[num_vehicles:] = 0
    restore = np.argsort(by_length, kind="stable")  # each vehicle's row in the sorted order

    def grouped(values):  # (vehicle, ...) in sorted order -> (chunk, vehicle in chunk, ...)
        return jax.tree.map(lambda a: a.reshape(-1, chunk, *a.shape[1:]), values)

    def vehicle_progress(done_chunks: int, _total_chunks: int) -> None:
        if problem.progress is not None:
            problem.progress(min(done_chunks * chunk, num_vehicles), num_vehicles)

    # Each vehicle's key gives its prior draws and, per epoch, its filter's and its redraw's keys.
    streams = jax.vmap(lambda k: jax.random.split(k, 1 + 2 * epochs))(problem.keys(key))
    draws = jax.vmap(lambda k: problem.prior.sample(k, (num_particles,)))(streams[:, 0])
    start = grid.indices(draws)  # on the host, to compile nothing
    compile_time, run_time = 0.0, 0.0
    epoch_log_evidence, pooled_means = [], []
    for epoch in range(epochs):
        keys, pool_keys = streams[:, 1 + 2 * epoch], streams[:, 2 + 2 * epoch]
        out, compiled_s, ran_s = map_vehicles(
            per_chunk,
            (grouped(keys[order]), grouped(ordered), grouped(start[order])),
            chunk=1,
            batch=None,
            progress=vehicle_progress,
            cache_key=cache_key,
        )
        out = jax.tree.map(lambda a: a.reshape(-1, *a.shape[2:])[restore], out)
        compile_time += compiled_s
        run_time += ran_s
        epoch_log_evidence.append(out.log_evidence)
        pooled_means.append(grid.values(out.index).mean(axis=(0, 1)))
        if epoch + 1 < epochs:
            # The paper's epochs: every vehicle's next start is drawn from all final particles.
            pool = jnp.asarray(out.index.reshape(-1, len(names)))
            picks = functools.partial(jax.random.randint, shape=(num_particles,), minval=0)
            start = pool[jax.vmap(functools.partial(picks, maxval=len(pool)))(pool_keys)]

    particles = grid.values(out.index)
    log_lik = problem.pointwise_scores(particles)
    vehicle_step = ("vehicle", "step")
    return one_chain_result(
        names,
        particles,
        log_lik,
        sample_stats={
            "particle_ess": (vehicle_step, out.ess),
            "resampled": (vehicle_step, np.asarray(arrays.mask) > 0),
            "unique_particles": (vehicle_step, out.unique),
            "particle_mean": (("vehicle", "step", "param"), out.mean),
            "convergence": (vehicle_step, out.convergence),
            "log_evidence": (("vehicle",), out.log_evidence),
            "epoch_log_evidence": (("epoch", "vehicle"), np.stack(epoch_log_evidence)),
            "epoch_pooled_mean": (("epoch", "param"), np.stack(pooled_means)),
        },
        prior=posterior_draws(names, np.asarray(draws)[:, None]),
        compile_time_s=compile_time,
        wall_time_s=run_time,
        options={
            "num_particles": num_particles,
            "epochs": epochs,
            "grid_steps": dict(zip(names, grid.step.tolist(), strict=True)),
            "resampler": "systematic",
            "dither": "uniform {-1, 0, +1} grid steps per parameter, clipped to the grid",
            "vehicle_chunk": vehicle_chunk,
        },
    )
