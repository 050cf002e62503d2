"""``bayesdrive simulate``: generate scenes from a preset or a fitted posterior."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from bayesdrive.cli.common import (
    ForceResults,
    check_json_out,
    console,
    emit_json,
    fail,
    results_command,
    results_folder,
)
from bayesdrive.data.atomic import write_atomic

PRESET_DIR = Path(__file__).resolve().parents[2] / "models" / "presets"


def _preset_path(name: str) -> Path | None:
    candidate = Path(name)
    if candidate.suffix == ".json" and candidate.exists():
        return candidate
    named = PRESET_DIR / f"{name}.json"
    return named if named.exists() else None


def _posterior_draw(key, result: Path, num_scenes: int, num_vehicles: int):
    import numpy as np

    from bayesdrive.drivers.registry import get_model
    from bayesdrive.inference.core.output import load_result, metadata
    from bayesdrive.simulation.generate import draw_pooled
    from bayesdrive.simulation.posterior import fixed_params, particles_by_vehicle

    tree = load_result(result)
    meta = metadata(tree)
    model = get_model(meta["model"])
    names = tuple(meta["params"])
    particles = np.stack(list(particles_by_vehicle(tree, names).values()))
    fixed = fixed_params(model, meta)
    return model, draw_pooled(key, model, names, particles, num_scenes, num_vehicles, fixed)


@results_command
def simulate(
    source: str = typer.Argument(
        ..., help="A preset name (models/presets), a preset .json, or a result.nc from fit."
    ),
    vehicles: int = typer.Option(16, help="Cars per generated scene."),
    duration: float = typer.Option(60.0, help="Seconds per scene."),
    scenes: int = typer.Option(20, help="Number of generated scenes."),
    seed: int = typer.Option(..., help="Seed of every random draw (recorded)."),
    dt: float = typer.Option(0.1, help="Step length (s)."),
    out: Path = typer.Option(..., help="Output directory."),
    json_out: str | None = typer.Option(None, "--json", help="Summary as JSON to a file or '-'."),
    force: ForceResults = False,
) -> None:
    """Generate scenes of VEHICLES cars for DURATION seconds; write trajectories, figures, summary."""
    # Imported here so that `bayesdrive simulate --help` does not import JAX.
    import jax
    import numpy as np
    import xarray as xr

    from bayesdrive.drivers.registry import get_model
    from bayesdrive.reports.scene_plots import plot_speed_gap_kde, plot_sweep
    from bayesdrive.simulation.generate import (
        START_SPEED_FRACTION,
        draw_preset,
        generate_scenes,
        load_preset,
        median_sweep,
    )

    check_json_out(json_out, force)
    key_params, key_scenes, key_sweep = jax.random.split(jax.random.key(seed), 3)
    preset_path = _preset_path(source)
    if preset_path is not None:
        preset = load_preset(preset_path)
        model = get_model(preset.model)
        params = draw_preset(key_params, model, preset, scenes, vehicles)
        label = preset.name
    elif Path(source).suffix == ".nc" and Path(source).exists():
        model, params = _posterior_draw(key_params, Path(source), scenes, vehicles)
        label = f"pooled posterior of {source}"
    else:
        raise fail(
            f"{source!r} is neither a preset in {PRESET_DIR} ("
            + ", ".join(sorted(p.stem for p in PRESET_DIR.glob("*.json")))
            + ") nor a result .nc file"
        )
    results = results_folder(out, "simulate", force=force)
    staged = results.path

    num_steps = round(duration / dt)
    started = time.perf_counter()
    with console.status(f"simulating {scenes} scenes of {vehicles} cars for {duration:g} s"):
        generated = jax.block_until_ready(
            generate_scenes(key_scenes, model, params, num_steps=num_steps, dt=dt)
        )
    elapsed = time.perf_counter() - started
    speeds = np.asarray(generated.v)
    gaps = np.asarray(generated.gap)[:, 1:]  # the first car drives on free road

    time_s = np.arange(num_steps + 1) * dt
    trajectories = xr.Dataset(
        {
            "x": (("scene", "vehicle", "time"), np.asarray(generated.x)),
            "v": (("scene", "vehicle", "time"), speeds),
            "gap": (("scene", "vehicle", "time"), np.asarray(generated.gap)),
        },
        coords={"time": time_s},
        attrs={"source": source, "seed": seed, "model": model.name, "dt": dt},
    )
    write_atomic(staged / "scenes.nc", lambda tmp: trajectories.to_netcdf(tmp, engine="h5netcdf"))

    sweep = median_sweep(key_sweep, model, params, duration_s=min(duration, 60.0), dt=dt)
    plot_speed_gap_kde(
        {label: (speeds[:, 1:], gaps)}, staged / "speed_gap_kde.png", f"generated scenes: {label}"
    )
    plot_sweep(
        sweep,
        dt,
        staged / "sweep.png",
        f"leader-follower sweep over desired-speed difference ({label}, median parameters)",
    )
    summary = {
        "source": source,
        "model": model.name,
        "seed": seed,
        "scenes": scenes,
        "vehicles": vehicles,
        "duration_s": duration,
        "dt_s": dt,
        "initial_condition": (
            f"common speed {START_SPEED_FRACTION} x the platoon's smallest v_des, "
            "IDM equilibrium gaps"
        ),
        "wall_time_s": elapsed,
        "speed_mps": {
            "mean": float(speeds.mean()),
            "q05": float(np.quantile(speeds, 0.05)),
            "q95": float(np.quantile(speeds, 0.95)),
        },
        "gap_m": {
            "median": float(np.median(gaps)),
            "q05": float(np.quantile(gaps, 0.05)),
            "min": float(gaps.min()),
        },
        "collisions": int(np.asarray(generated.collision).any(axis=-1).sum()),
        "hard_braking": int(np.asarray(generated.hard_braking).sum()),
        "files": ["scenes.nc", "speed_gap_kde.png", "sweep.png", "summary.json"],
    }
    emit_json(summary, str(staged / "summary.json"))
    results.commit()
    if emit_json(summary, json_out):
        return
    console.print(
        f"{scenes} scenes x {vehicles} cars x {duration:g} s from {label}: mean speed "
        f"{summary['speed_mps']['mean']:.1f} m/s, median gap {summary['gap_m']['median']:.1f} m, "
        f"{summary['collisions']} collisions, {summary['hard_braking']} hard-braking steps "
        f"({elapsed:.1f} s) -> {out}"
    )
