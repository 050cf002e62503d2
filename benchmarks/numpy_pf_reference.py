"""The paper's particle filter in plain vectorised NumPy: the reference `bench_filters.py` times
`pf` against, in the same process (filter time) and as a whole process of its own (start-up,
reading the data, filtering, writing the posterior and its summary).

It imports no JAX: a benchmark reference has to restate the IDM, and `bench_filters.py` checks
this restatement (constants and log-density) against `bayesdrive.drivers.idm` before anything is
timed. It does what a careful NumPy author would: the free-road power by squaring, the stop
term's normal log-CDF only on the steps that end in a stop, one `searchsorted` for the
systematic resampling of every vehicle.

    python benchmarks/numpy_pf_reference.py DATA --particles N --grid GRID.json --out FILE.npz

writes the posterior draws (vehicle, particle, parameter) to FILE.npz and, as `bayesdrive fit`'s
summary.json does, each vehicle's and parameter's posterior mean, sd and 5%/95% quantiles to
FILE.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.special import log_ndtr

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bayesdrive.data import registry  # noqa: E402
from bayesdrive.data.views import LENGTH_BUCKET, FollowerArrays, follower_arrays  # noqa: E402

# The IDM's constants as bayesdrive.drivers.idm defines them (bench_filters.py asserts equality).
DELTA = 4
STOP_SPEED = 1e-3
MIN_GAP = 0.1
STEP_FIELDS = ("v", "next_v", "dx", "gap", "lead_v", "has_leader")


def step_logpdf(p: dict, v, next_v, dx, gap, lead_v, has_leader, dt):
    """The IDM one-step log-density (bayesdrive.drivers.execution_noise.step_logpdf) in NumPy, float64."""
    ratio = v / p["v_des"]
    squared = ratio * ratio
    free = 1.0 - squared * squared  # DELTA = 4
    dynamic = v * p["tau"] + v * (v - lead_v) / (2.0 * np.sqrt(p["a_max"] * p["b_pref"]))
    desired = p["d_min"] + np.maximum(0.0, dynamic)
    safe_gap = np.maximum(np.where(has_leader > 0, gap, 1.0), MIN_GAP)
    interaction = np.where(has_leader > 0, (desired / safe_gap) ** 2, 0.0)
    acc = p["a_max"] * (free - interaction)
    sd = 0.5 * p["sigma"] * dt**2
    z = (dx - (v * dt + 0.5 * acc * dt**2)) / sd
    out = -0.5 * z**2 - np.log(sd) - 0.5 * np.log(2 * np.pi)
    stop = np.broadcast_to(next_v <= STOP_SPEED, out.shape)
    if stop.any():
        upper = (STOP_SPEED - v - acc * dt) / (p["sigma"] * dt)
        out[stop] = log_ndtr(np.broadcast_to(upper, out.shape)[stop])
    return out


def filter_particles(
    rng: np.random.Generator,
    arrays: FollowerArrays,
    grid: dict,
    fixed: dict,
    start: np.ndarray,
) -> np.ndarray:
    """The paper's filter over all vehicles at once: weight, systematic resampling, dithering.

    ``grid`` holds the inferred parameters' ``names``, ``first``, ``step`` and ``size``;
    ``fixed`` the values of the others. Like the JAX engine it skips padding: vehicles sorted by
    series length, each step computes only the vehicles whose series has not ended.
    """
    num_particles = start.shape[1]
    first, step, size = (np.asarray(grid[k]) for k in ("first", "step", "size"))
    live = arrays.mask > 0
    length = np.where(live.any(axis=1), live.shape[1] - np.argmax(live[:, ::-1], axis=1), 0)
    order = np.argsort(-length, kind="stable")
    steps = {name: getattr(arrays, name)[order] for name in (*STEP_FIELDS, "mask")}
    index = start[order].copy()
    for t in range(arrays.mask.shape[1]):
        active = int(np.sum(length > t))  # a prefix of the sorted vehicles
        if active == 0:
            break
        rows = np.arange(active)[:, None]
        current = index[:active]
        values = first + current * step
        params = fixed | {name: values[..., k] for k, name in enumerate(grid["names"])}
        inputs = {name: steps[name][:active, t, None] for name in STEP_FIELDS}
        log_weight = step_logpdf(params, **inputs, dt=arrays.dt)
        weight = np.exp(log_weight - log_weight.max(axis=1, keepdims=True))
        cdf = np.cumsum(weight, axis=1)
        cdf /= cdf[:, -1:]
        positions = (rng.random((active, 1)) + np.arange(num_particles)) / num_particles
        # One searchsorted for all vehicles: row r's cdf and positions are shifted into (r, r+1].
        found = np.searchsorted((cdf + rows).ravel(), (positions + rows).ravel(), side="right")
        parents = np.clip(found.reshape(active, -1) - rows * num_particles, 0, num_particles - 1)
        resampled = np.take_along_axis(current, parents[..., None], axis=1)
        dithered = np.clip(resampled + rng.integers(-1, 2, size=current.shape), 0, size - 1)
        index[:active] = np.where(steps["mask"][:active, t, None, None] > 0, dithered, current)
    return index[np.argsort(order)]


def start_indices(rng: np.random.Generator, grid: dict, lower, upper, shape) -> np.ndarray:
    """Prior draws on the box, snapped to the grid: (vehicles, particles, parameters)."""
    draws = rng.uniform(np.asarray(lower), np.asarray(upper), (*shape, len(grid["names"])))
    first, step, size = (np.asarray(grid[k]) for k in ("first", "step", "size"))
    return np.clip(np.round((draws - first) / step), 0, size - 1).astype(np.int64)


def trimmed(arrays: FollowerArrays) -> FollowerArrays:
    """The arrays cut to the length bucket of their longest usable series (less padding)."""
    last = int(np.max(np.nonzero(arrays.mask.any(axis=0))[0])) + 1
    width = int(np.ceil(last / LENGTH_BUCKET) * LENGTH_BUCKET)
    per_step = {n: v[:, :width] for n, v in arrays._asdict().items() if isinstance(v, np.ndarray)}
    return arrays._replace(**per_step)


def main(argv: list[str] | None = None) -> int:
    """The whole-process reference: read, filter every follower's 'all' window, save the
    posterior and its summary."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", help="a data set name or path, as `bayesdrive fit` takes it")
    parser.add_argument("--particles", type=int, required=True)
    parser.add_argument("--grid", type=Path, required=True, help="JSON written by bench_filters")
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    spec = json.loads(args.grid.read_text())
    arrays = trimmed(follower_arrays(registry.load(args.data), window="all"))
    rng = np.random.default_rng(args.seed)
    start = start_indices(
        rng, spec["grid"], spec["lower"], spec["upper"], (arrays.mask.shape[0], args.particles)
    )
    started = time.perf_counter()
    index = filter_particles(rng, arrays, spec["grid"], spec["fixed"], start)
    print(f"filter {time.perf_counter() - started:.2f} s", flush=True)
    grid = spec["grid"]
    draws = np.asarray(grid["first"]) + index * np.asarray(grid["step"])
    vehicles = [str(v) for v in arrays.vehicle_ids]
    np.savez(args.out, posterior=draws, names=grid["names"], vehicles=vehicles)
    q05, q95 = np.quantile(draws, [0.05, 0.95], axis=1)
    mean, sd = draws.mean(axis=1), draws.std(axis=1)
    summary = {
        vehicle: {
            name: {"mean": mean[i, k], "sd": sd[i, k], "q05": q05[i, k], "q95": q95[i, k]}
            for k, name in enumerate(grid["names"])
        }
        for i, vehicle in enumerate(vehicles)
    }
    args.out.with_suffix(".json").write_text(json.dumps({"vehicles": summary}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
