"""Speed of the particle engines on real NGSIM I-80 chain vehicles, beside a NumPy reference.

* ``pf`` (the paper's filter) on every follower of ``ngsim_i80_chains`` (window "all"), against a
  plain vectorised NumPy implementation of the same filter (the same per-step work: weight every
  particle by the exact IDM step density, systematic resampling per vehicle, dithering) run in the
  same process on the same arrays. Throughput is particle-steps per second: vehicles x particles
  x steps / wall time, counting usable steps. Both skip padding the same way: vehicles sorted by
  series length, steps past the end of every series in a chunk (JAX) or of a vehicle (NumPy)
  are not computed.
* ``smc`` (resample-move) on a subset of vehicles: particle-steps per second and one-step
  likelihood evaluations per second, rejuvenation included (each move scores every particle on
  the steps seen so far, in blocks of 64), with vehicles run one after another (``vehicle_batch=1``,
  the default) and vectorised in batches (where ``lax.cond`` becomes a select that pays for the
  rejuvenation at every step).

Compile time is reported apart (ahead-of-time compilation, excluded from the wall times). The
machine is shared: its load average is recorded with the table. Writes ``reports/filter_speed.md``
(or ``--out``). Run: ``python benchmarks/bench_filters.py [--particles 1024]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import log_ndtr

from bayesdrive.data import registry
from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.data.views import LENGTH_BUCKET, FollowerArrays, follower_arrays
from bayesdrive.drivers.base import CarFollowingInputs, EgoState
from bayesdrive.drivers.idm import DELTA, IDM, MIN_GAP, STOP_SPEED
from bayesdrive.inference import pf, smc
from bayesdrive.inference.fit import first_vehicles
from bayesdrive.inference.vehicles import clear_compiled

PARAMS = ("v_des", "d_min", "tau", "a_max", "b_pref", "sigma")
SEED = 0
# Compile times are the least of this many fresh compilations: on a shared machine the others'
# load only ever adds to a compile's wall time.
COMPILE_REPEATS = 3


# --- the NumPy reference -----------------------------------------------------------------------
# A benchmark reference has to restate the IDM in NumPy; check_reference() proves it equal to the
# model's own density before anything is timed.
def numpy_step_logpdf(p: dict, v, next_v, dx, gap, lead_v, has_leader, dt):
    """The IDM one-step log-density (bayesdrive.drivers.idm.step_logpdf) in NumPy, float64."""
    free = 1.0 - (v / p["v_des"]) ** DELTA
    dynamic = v * p["tau"] + v * (v - lead_v) / (2.0 * np.sqrt(p["a_max"] * p["b_pref"]))
    desired = p["d_min"] + np.maximum(0.0, dynamic)
    safe_gap = np.maximum(np.where(has_leader > 0, gap, 1.0), MIN_GAP)
    interaction = np.where(has_leader > 0, (desired / safe_gap) ** 2, 0.0)
    acc = p["a_max"] * (free - interaction)
    sd = 0.5 * p["sigma"] * dt**2
    z = (dx - (v * dt + 0.5 * acc * dt**2)) / sd
    moving = -0.5 * z**2 - np.log(sd) - 0.5 * np.log(2 * np.pi)
    stopped = log_ndtr(-(v + acc * dt) / (p["sigma"] * dt))
    return np.where(next_v <= STOP_SPEED, stopped, moving)


def numpy_pf(rng: np.random.Generator, arrays: FollowerArrays, grid: pf.Grid, start: np.ndarray):
    """The paper's filter over all vehicles at once: weight, systematic resampling, dithering.

    Like the JAX engine it skips padding: vehicles sorted by series length, each step computes
    only the vehicles whose series has not ended.
    """
    num_particles = start.shape[1]
    fixed = {s.name: s.default for s in IDM.specs}
    live = arrays.mask > 0
    length = np.where(live.any(axis=1), live.shape[1] - np.argmax(live[:, ::-1], axis=1), 0)
    order = np.argsort(-length, kind="stable")
    steps = {
        name: getattr(arrays, name)[order]
        for name in ("v", "next_v", "dx", "gap", "lead_v", "has_leader", "mask")
    }
    index = start[order].copy()
    for t in range(arrays.mask.shape[1]):
        active = int(np.sum(length > t))  # a prefix of the sorted vehicles
        if active == 0:
            break
        rows = np.arange(active)[:, None]
        current = index[:active]
        values = grid.first + current * grid.step
        params = fixed | {name: values[..., k] for k, name in enumerate(grid.names)}
        step = {name: steps[name][:active, t, None] for name in steps if name != "mask"}
        log_weight = numpy_step_logpdf(params, **step, dt=arrays.dt)
        weight = np.exp(log_weight - log_weight.max(axis=1, keepdims=True))
        cdf = np.cumsum(weight, axis=1)
        cdf /= cdf[:, -1:]
        positions = (rng.random((active, 1)) + np.arange(num_particles)) / num_particles
        # One searchsorted for all vehicles: row r's cdf and positions are shifted into (r, r+1].
        found = np.searchsorted((cdf + rows).ravel(), (positions + rows).ravel(), side="right")
        parents = np.clip(found.reshape(active, -1) - rows * num_particles, 0, num_particles - 1)
        resampled = np.take_along_axis(current, parents[..., None], axis=1)
        dithered = np.clip(resampled + rng.integers(-1, 2, size=current.shape), 0, grid.size - 1)
        index[:active] = np.where(steps["mask"][:active, t, None, None] > 0, dithered, current)
    return index[np.argsort(order)]


def check_reference(arrays: FollowerArrays) -> float:
    """Largest |NumPy - model| log-density over random prior draws on real steps (float64 model
    evaluation would be closer; float32 JAX differs by ~1e-4 on densities of order 10)."""
    rng = np.random.default_rng(SEED)
    box = IDM.prior(PARAMS)
    theta = rng.uniform(np.asarray(box.lower), np.asarray(box.upper), size=(256, len(PARAMS)))
    live = np.argwhere(arrays.mask > 0)[:256]
    step = {
        n: getattr(arrays, n)[live[:, 0], live[:, 1]]
        for n in ("v", "next_v", "dx", "gap", "lead_v", "has_leader")
    }
    ours = numpy_step_logpdf(dict(zip(PARAMS, theta.T, strict=True)), **step, dt=arrays.dt)

    def model(th, v, next_v, dx, gap, lead_v, has_leader):
        params = IDM.params_type(*th)
        inputs = CarFollowingInputs(gap, lead_v, has_leader, arrays.dt)
        return IDM.transition_logpdf(params, EgoState(0.0, v), EgoState(dx, next_v), inputs)

    theirs = jax.vmap(model)(
        jnp.asarray(theta),
        *(jnp.asarray(step[n]) for n in ("v", "next_v", "dx", "gap", "lead_v", "has_leader")),
    )
    return float(np.max(np.abs(ours - np.asarray(theirs)) / np.maximum(1.0, np.abs(ours))))


# --- helpers ---------------------------------------------------------------------------------------
def trimmed(arrays: FollowerArrays) -> FollowerArrays:
    """The arrays cut to the length bucket of their longest usable series (less padding)."""
    last = int(np.max(np.nonzero(arrays.mask.any(axis=0))[0])) + 1
    width = int(np.ceil(last / LENGTH_BUCKET) * LENGTH_BUCKET)
    per_step = {n: v[:, :width] for n, v in arrays._asdict().items() if isinstance(v, np.ndarray)}
    return arrays._replace(**per_step)


def row(name: str, particle_steps: float, seconds: float, compile_s: float, note: str) -> str:
    return (
        f"| {name} | {particle_steps:.3g} | {seconds:.2f} | {particle_steps / seconds:.3g} | "
        f"{compile_s:.2f} | {note} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--particles", type=int, default=1024)
    parser.add_argument("--smc-vehicles", type=int, default=24)
    parser.add_argument("--smc-particles", type=int, default=512)
    parser.add_argument("--batch-vehicles", type=int, default=4)
    parser.add_argument("--out", type=Path, default=Path("reports/filter_speed.md"))
    args = parser.parse_args()
    load_before = os.getloadavg()

    traj = registry.load("ngsim_i80_chains")
    arrays = trimmed(follower_arrays(traj, window="all"))
    num_vehicles, num_steps = arrays.mask.shape
    usable = int(arrays.mask.sum())
    reference_error = check_reference(arrays)
    assert reference_error < 1e-3, f"NumPy reference disagrees with the model: {reference_error}"
    lines = []

    # pf in JAX, all vehicles.
    n = args.particles
    compile_times = []
    for _ in range(COMPILE_REPEATS):
        clear_compiled()
        result = pf.run(jax.random.key(SEED), arrays, model=IDM, params=PARAMS, num_particles=n)
        compile_times.append(result.compile_time_s)
    pf_compile = min(compile_times)
    # The timed run reuses the compiled filter; its CPU time counts every thread JAX used.
    cpu_started = time.process_time()
    result = pf.run(jax.random.key(SEED), arrays, model=IDM, params=PARAMS, num_particles=n)
    jax_cpu = time.process_time() - cpu_started
    pf_steps = usable * n
    lines.append(
        row(
            "pf, JAX (64 vehicles vectorised per chunk, scan over steps)",
            pf_steps,
            result.wall_time_s,
            pf_compile,
            f"{num_vehicles} vehicles x {n} particles; CPU time {jax_cpu:.2f} s (all threads, "
            "incl. scoring the log-likelihood group)",
        )
    )
    jax_rate = pf_steps / result.wall_time_s

    # The same filter in NumPy, from the same kind of start (prior draws snapped to the grid).
    grid = pf.make_grid(IDM, PARAMS)
    rng = np.random.default_rng(SEED)
    box = IDM.prior(PARAMS)
    draws = rng.uniform(
        np.asarray(box.lower), np.asarray(box.upper), (num_vehicles, n, len(PARAMS))
    )
    start = np.clip(np.round((draws - grid.first) / grid.step), 0, grid.size - 1).astype(np.int64)
    started, cpu_started = time.perf_counter(), time.process_time()
    numpy_pf(rng, arrays, grid, start)
    numpy_seconds = time.perf_counter() - started
    numpy_cpu = time.process_time() - cpu_started
    lines.append(
        row(
            "pf, NumPy reference (vectorised over vehicles and particles)",
            pf_steps,
            numpy_seconds,
            0.0,
            f"same arrays, same per-step work; CPU time {numpy_cpu:.2f} s",
        )
    )
    speedup = jax_rate / (pf_steps / numpy_seconds)
    cpu_speedup = numpy_cpu / jax_cpu

    # smc on a subset, sequential vehicles (default) and vectorised batches.
    subset = trimmed(first_vehicles(arrays, args.smc_vehicles))
    smc_lines = []
    for label, count, batch in (
        ("smc, vehicles one after another (default)", args.smc_vehicles, 1),
        (
            f"smc, vehicles vectorised {args.batch_vehicles} at a time",
            args.batch_vehicles,
            args.batch_vehicles,
        ),
        ("smc, the same vehicles one after another", args.batch_vehicles, 1),
    ):
        data = trimmed(first_vehicles(subset, count))
        m = args.smc_particles
        out = smc.run(
            jax.random.key(SEED),
            data,
            model=IDM,
            params=PARAMS,
            num_particles=m,
            vehicle_batch=batch,
            vehicle_chunk=count,
            sequential=True,
        )
        steps = int(data.mask.sum())
        resampled = out.sample_stats["resampled"][1]
        # A paired move (random walk + independent) scores the series twice.
        per_move = 2 if out.options["independent"] else 1
        moves = out.options["num_moves"] * per_move
        # A move scores the blocks of SCORE_BLOCK steps up to the current step. The closing
        # tempering stage scores each vehicle's whole series once for its fresh prior draws, then
        # temper_moves times per stage and, at the end, as many times as its closing moves ran.
        last_live = data.mask.shape[1] - 1 - np.argmax(data.mask[:, ::-1] > 0, axis=1)
        rejuvenated = np.nonzero(resampled)[1]
        blocks = (rejuvenated // smc.SCORE_BLOCK + 1) * smc.SCORE_BLOCK
        whole = (last_live // smc.SCORE_BLOCK + 1) * smc.SCORE_BLOCK
        stages = np.asarray(out.sample_stats["temper_stages"][1]).reshape(-1)[: len(whole)]
        final_moves = np.asarray(out.sample_stats["final_moves"][1]).reshape(-1)[: len(whole)]
        closing_scans = 1 + per_move * (stages * out.options["temper_moves"] + final_moves)
        events = len(rejuvenated)
        padded = data.mask.shape[1]
        evaluations = data.mask.size * m + m * (
            moves * int(blocks.sum()) + int(whole @ closing_scans)
        )
        smc_lines.append(
            row(
                label,
                steps * m,
                out.wall_time_s,
                out.compile_time_s,
                f"{count} vehicles x {m} particles, {padded} padded steps; {events} rejuvenations "
                f"x {moves} moves, {int(stages.sum())} tempering stages; "
                f"{evaluations / out.wall_time_s:.3g} likelihood evaluations/s",
            )
        )

    header = [
        "| run | particle-steps (usable) | wall time (s) | particle-steps/s | compile (s) | notes |",
        "|---|---|---|---|---|---|",
    ]
    text = "\n".join(
        [
            "# Filter speed",
            "",
            f"Generated by `benchmarks/bench_filters.py` on {platform.node() or 'this machine'} "
            f"({os.cpu_count()} cores, {platform.processor() or platform.machine()}), jax "
            f"{jax.__version__}, float32, seed {SEED}. Load average when it started: "
            f"{load_before[0]:.1f} (the machine is shared with other work: absolute numbers vary, "
            "the ratios less).",
            "",
            f"Data: `ngsim_i80_chains`, window `all`: {num_vehicles} followers, {usable} usable "
            f"steps, padded to {num_steps}. Parameters: all six IDM parameters "
            f"({', '.join(PARAMS)}). Wall times exclude compilation (ahead-of-time compiled).",
            "",
            *header,
            *lines,
            *smc_lines,
            "",
            f"**pf speed-up over the NumPy reference: {speedup:.1f}x in wall time, "
            f"{cpu_speedup:.1f}x in CPU time** (target >= 5x); pf compile "
            f"{pf_compile:.2f} s (target < 5 s; least of {COMPILE_REPEATS} compilations, all: "
            f"{', '.join(f'{t:.2f}' for t in compile_times)} s).",
            "",
            f"The NumPy reference's log-density matches `IDM.transition_logpdf` to a relative "
            f"{reference_error:.1e} on real steps (float32 model).",
            "",
            "smc's likelihood evaluations count the reweighting of every particle on every padded "
            "step, per rejuvenation every move scoring every particle on the steps seen so far, "
            "and the closing tempering stage (every particle scored on the whole series once, "
            "then once per move of every stage and per final move), rounded up to blocks of "
            f"{smc.SCORE_BLOCK}. Vectorising vehicles turns rejuvenation's `lax.cond` into a "
            "select that runs it at every step, so that row computes far more than it counts; "
            "compare the two rows on the same vehicles.",
            "",
        ]
    )
    write_text_atomic(args.out, text)
    print(text)


if __name__ == "__main__":
    main()
