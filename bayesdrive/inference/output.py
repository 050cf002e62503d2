"""The one result layout every engine returns and saves: an ArviZ 1.x ``xarray.DataTree``.

Groups (dims in brackets):

* ``posterior``: one variable per inferred parameter [chain, draw, vehicle]. Particle engines have
  chain = 1 and draw = particle (equally weighted); MCMC engines fill real chains.
* ``sample_stats``: engine diagnostics with explicit dims, e.g. ``ess`` [vehicle, step],
  ``resampled`` [vehicle, step], ``log_evidence`` [vehicle], ``acceptance`` [vehicle, step].
* ``log_likelihood``: variable ``dx`` [chain, draw, vehicle, step], the log-density of each observed
  step (named after the observed position increment it scores) under each posterior draw, 0 on
  masked steps, so ``arviz.loo`` and ``arviz.compare`` work on a result. Engines may score a thinned
  set of draws; its ``draw`` coordinate then names the posterior draws scored.
* ``observed_data``: the :class:`~bayesdrive.data.views.FollowerArrays` the engine saw [vehicle, step].

Root attributes hold the metadata (:data:`REQUIRED_METADATA` plus versions, the code that made
the result (``code``: version, git commit and whether the code was clean, see
:mod:`bayesdrive.data.provenance`) and creation time). The only attributes that differ between two
runs of the same command on the same machine are :data:`RUN_DEPENDENT_ATTRS`: the creation time
and the measured wall and compile times.
netCDF attributes take only strings and numbers, so lists, dicts, booleans and None are stored as
JSON text; the attribute ``json_attrs`` names those, and :func:`metadata` decodes them. Opening a
result needs nothing but xarray or ArviZ: ``xarray.open_datatree(path)`` or
``arviz.from_netcdf(path)``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from datetime import UTC, datetime
from importlib.metadata import version
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import xarray as xr

from bayesdrive.data.atomic import write_atomic
from bayesdrive.data.provenance import code_provenance
from bayesdrive.data.views import SPLIT_RULE, FollowerArrays

__all__ = [
    "OBSERVED_VARIABLE",
    "REQUIRED_METADATA",
    "RUN_DEPENDENT_ATTRS",
    "EngineResult",
    "build_tree",
    "load_result",
    "metadata",
    "particle_log_likelihood",
    "particle_posterior",
    "save_result",
    "thinned_draws",
]

# The quantity the likelihood scores (see bayesdrive.drivers.idm); names the log_likelihood variable.
OBSERVED_VARIABLE = "dx"
REQUIRED_METADATA = (
    "engine",
    "model",
    "params",
    "fixed",
    "seed",
    "data_source",
    "window",
    "num_particles",
    "flagged_samples",
)
# Timestamps and timings: everything else in a result is a function of its inputs and seed.
RUN_DEPENDENT_ATTRS = ("created_at", "wall_time_s", "compile_time_s")
_VERSIONED = ("bayesdrive", "jax", "numpyro", "arviz", "xarray")


class EngineResult(NamedTuple):
    """What an engine hands to :func:`build_tree` (numpy arrays; see the module docstring).

    posterior: parameter name -> (chain, draw, vehicle).
    sample_stats: name -> (dims, values) with dims among vehicle, step, param, epoch, ...
    log_likelihood: (chain, draw, vehicle, step) for the draws ``log_likelihood_draws`` (None: all).
    compile_time_s: time spent compiling; wall_time_s: the inference itself, compilation excluded.
    options: the engine's settings, recorded in the metadata.
    """

    posterior: dict[str, np.ndarray]
    sample_stats: dict[str, tuple[tuple[str, ...], np.ndarray]]
    log_likelihood: np.ndarray
    log_likelihood_draws: np.ndarray | None
    compile_time_s: float
    wall_time_s: float
    options: dict[str, Any]


def thinned_draws(num_draws: int, num_scored: int) -> np.ndarray:
    """Indices of ``num_scored`` evenly spaced draws out of ``num_draws`` (all when fewer)."""
    num_scored = min(num_scored, num_draws)
    return (np.arange(num_scored) * num_draws) // num_scored


def particle_posterior(names: tuple[str, ...], particles: np.ndarray) -> dict[str, np.ndarray]:
    """Equally weighted particles (vehicle, particle, param) as posterior arrays (1, N, vehicle)."""
    return {name: particles[:, :, i].T[None].astype(np.float64) for i, name in enumerate(names)}


def particle_log_likelihood(log_lik: np.ndarray) -> np.ndarray:
    """Per-vehicle scores (vehicle, draw, step) as the group's (chain = 1, draw, vehicle, step)."""
    return np.asarray(log_lik).transpose(1, 0, 2)[None]


def build_tree(
    *,
    posterior: Mapping[str, np.ndarray],
    sample_stats: Mapping[str, tuple[tuple[str, ...], np.ndarray]],
    log_likelihood: np.ndarray,
    arrays: FollowerArrays,
    metadata: Mapping[str, Any],
    log_likelihood_draws: np.ndarray | None = None,
) -> xr.DataTree:
    """Assemble the result tree; ``metadata`` needs :data:`REQUIRED_METADATA` (versions, creation
    time and the split rule are added here)."""
    missing = [k for k in REQUIRED_METADATA if k not in metadata]
    if missing:
        raise ValueError(f"result metadata lacks {missing}")
    num_vehicles, num_steps = arrays.mask.shape
    coords = {
        "vehicle": list(arrays.vehicle_ids),
        "step": np.arange(num_steps),
        "param": list(metadata["params"]),
    }

    first = next(iter(posterior.values()))
    num_chains, num_draws, _ = np.shape(first)
    for name, values in posterior.items():
        if np.shape(values) != (num_chains, num_draws, num_vehicles):
            raise ValueError(
                f"posterior {name!r} has shape {np.shape(values)}, expected "
                f"(chain, draw, vehicle) = ({num_chains}, {num_draws}, {num_vehicles})"
            )
    draw_coords = {"chain": np.arange(num_chains), "draw": np.arange(num_draws)}
    posterior_ds = xr.Dataset(
        {name: (("chain", "draw", "vehicle"), np.asarray(v)) for name, v in posterior.items()},
        coords={**draw_coords, "vehicle": coords["vehicle"]},
    )

    scored = np.arange(num_draws) if log_likelihood_draws is None else log_likelihood_draws
    expected = (num_chains, len(scored), num_vehicles, num_steps)
    if np.shape(log_likelihood) != expected:
        raise ValueError(
            f"log_likelihood has shape {np.shape(log_likelihood)}, expected "
            f"(chain, draw, vehicle, step) = {expected}"
        )
    log_lik_ds = xr.Dataset(
        {OBSERVED_VARIABLE: (("chain", "draw", "vehicle", "step"), np.asarray(log_likelihood))},
        coords={
            "chain": draw_coords["chain"],
            "draw": np.asarray(scored),
            "vehicle": coords["vehicle"],
            "step": coords["step"],
        },
    )

    stats_ds = xr.Dataset(
        {name: (dims, np.asarray(values)) for name, (dims, values) in sample_stats.items()}
    )
    used_dims = set(stats_ds.dims)
    stats_ds = stats_ds.assign_coords({d: c for d, c in coords.items() if d in used_dims})

    observed_ds = xr.Dataset(
        {
            name: (("vehicle", "step"), np.asarray(getattr(arrays, name)))
            for name in ("t", "v", "next_v", "dx", "gap", "lead_v", "has_leader", "mask")
        },
        coords={"vehicle": coords["vehicle"], "step": coords["step"]},
        attrs={"dt": float(arrays.dt)},
    )

    attrs = {
        **metadata,
        "split_rule": SPLIT_RULE,
        "versions": {name: version(name) for name in _VERSIONED},
        "code": code_provenance(),
        "created_at": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    tree = xr.DataTree.from_dict(
        {
            "posterior": posterior_ds,
            "sample_stats": stats_ds,
            "log_likelihood": log_lik_ds,
            "observed_data": observed_ds,
        }
    )
    tree.attrs = _encode_attrs(attrs)
    return tree


def _encode_attrs(attrs: Mapping[str, Any]) -> dict[str, Any]:
    encoded, as_json = {}, []
    for key, value in attrs.items():
        if isinstance(value, str | int | float) and not isinstance(value, bool):
            encoded[key] = value
        else:
            encoded[key] = json.dumps(value)
            as_json.append(key)
    encoded["json_attrs"] = json.dumps(as_json)
    return encoded


def metadata(tree: xr.DataTree) -> dict[str, Any]:
    """The root metadata with JSON-encoded attributes decoded back to lists, dicts and None."""
    attrs = dict(tree.attrs)
    as_json = json.loads(attrs.pop("json_attrs", "[]"))
    return {k: json.loads(v) if k in as_json else v for k, v in attrs.items()}


def save_result(tree: xr.DataTree, path: str | Path) -> Path:
    """Write the tree as netCDF (h5netcdf) atomically: a crash leaves no partial file."""
    path = Path(path)
    write_atomic(path, lambda tmp: tree.to_netcdf(tmp, engine="h5netcdf"))
    return path


def load_result(path: str | Path) -> xr.DataTree:
    """Read a saved result fully into memory (the file is closed again)."""
    return xr.load_datatree(Path(path), engine="h5netcdf")
