"""The one result layout every engine returns and saves: an ArviZ 1.x ``xarray.DataTree``.

Groups (dims in brackets):

* ``posterior``: one variable per inferred parameter [chain, draw, vehicle], with ``units`` and
  ``long_name`` attributes from the model's parameter specs. Particle engines have chain = 1 (or
  one chain per independent replicate) and draw = particle (equally weighted); MCMC engines fill
  real chains.
* ``prior``: prior draws of the same variables [chain, draw, vehicle], where the engine has them.
* ``sample_stats``: engine diagnostics with explicit dims, e.g. ``particle_ess`` [vehicle, step]
  (the filters' effective particle count, not ArviZ's ``ess``), ``resampled`` [vehicle, step],
  ``log_evidence`` [vehicle], ``acceptance`` [vehicle, step].
* ``log_likelihood``: variable ``dx`` [chain, draw, obs] (float32), the log-density of each real
  observed step (named after the observed position increment it scores) under every posterior
  draw. ``obs`` runs over the usable (vehicle, step) pairs with a full history of usable steps
  before them (:attr:`~bayesdrive.data.views.FollowerArrays.full_history_mask`): a model that
  reads its past scores no step without one, so every model of the same data holds the same
  observations and ``arviz.compare`` compares like for like. It carries the non-dimension
  coordinates ``vehicle``, ``step`` and ``t`` (s), so ``arviz.loo``, ``arviz.compare`` and
  ArviZ's comparison plots work on a result as it is. Root metadata ``psis_loo``
  (:func:`psis_loo_check`) says whether PSIS-LOO can be trusted on it, and what to use if not.
  A fit with ``pointwise=False`` has no such group (a smaller file, no scoring; nothing to
  compare models by).
* ``observed_data``: the :class:`~bayesdrive.data.views.FollowerArrays` the engine saw [vehicle, step].

``posterior``, ``prior`` and ``sample_stats`` carry ArviZ's ``inference_library`` and
``inference_library_version`` attributes. Root attributes hold the metadata
(:data:`REQUIRED_METADATA`, plus ``num_chains`` and ``num_draws`` read off the posterior, versions,
the code that made the result (``code``: version, git commit and whether the code was clean, see
:mod:`bayesdrive.data.provenance`) and creation time). The only attributes that differ between two
runs of the same command on the same machine are :data:`RUN_DEPENDENT_ATTRS`: the creation time
and the measured wall and compile times. A fit on read data also records ``input_sha256`` (file path -> sha256 of every
input file) and ``input_repairs`` (the changes the reader made to the input). netCDF attributes take only strings and numbers, so lists, dicts, booleans and
None are stored as JSON text; the attribute ``json_attrs`` names those, and :func:`metadata`
decodes them. Opening a result needs nothing but xarray or ArviZ: ``xarray.open_datatree(path)`` or
``arviz.from_netcdf(path)``; :func:`load_result` also reads results saved in the older layout
(padded, thinned log-likelihood; ``ess`` for ``particle_ess``) and says what it converted.
"""

from __future__ import annotations

import itertools
import json
import logging
from collections.abc import Callable, Mapping, Sequence
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any, NamedTuple, TypedDict

import numpy as np
import xarray as xr

from bayesdrive.data.atomic import write_atomic
from bayesdrive.data.provenance import code_provenance
from bayesdrive.data.views import SPLIT_RULE, FollowerArrays, full_history_mask, history_steps
from bayesdrive.drivers.base import DriverModel, ParamSpec

__all__ = [
    "OBSERVED_VARIABLE",
    "PSIS_ALTERNATIVE",
    "REQUIRED_METADATA",
    "RUN_DEPENDENT_ATTRS",
    "EngineInputs",
    "EngineResult",
    "build_tree",
    "load_result",
    "metadata",
    "psis_loo_check",
    "save_result",
    "set_metadata",
    "thinned_draws",
]

log = logging.getLogger(__name__)

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
    "flagged_samples",
)
# Timestamps and timings: everything else in a result is a function of its inputs and seed.
RUN_DEPENDENT_ATTRS = ("created_at", "wall_time_s", "compile_time_s")
_VERSIONED = ("bayesdrive", "jax", "numpyro", "arviz", "xarray")
# Groups that describe draws, so ArviZ's provenance attributes belong on them.
_DRAW_GROUPS = ("posterior", "prior", "sample_stats")
# What to compare models by where PSIS-LOO cannot be trusted (the README says the same).
PSIS_ALTERNATIVE = (
    "compare the models by their held-out predictive density instead (bayesdrive criticize "
    "scores each extension on the held-out window), or refit with nuts, or with smc and more "
    "particles where its draws hold copies"
)
# Vehicle ids named in a problem line before the rest are counted.
_NAMED_VEHICLES = 10


class EngineInputs(TypedDict, total=False):
    """The keyword arguments every engine takes (``fit`` passes them all): the driver ``model``
    (required), the inferred ``params`` (None: all of the model's), ``fixed`` values of the others
    (None: the model's defaults), ``num_particles`` (the run's size: particles, or posterior draws
    in all; each engine has its own default), the ``prior`` (None: the model's uniform box; it
    needs ``logpdf(theta)`` and, for the engines that draw from it, ``sample(key, shape)``),
    ``progress(done, total)``, called as vehicles finish, and ``pointwise`` (default True): whether
    the result holds the log_likelihood group (False: an engine that scores its draws after
    sampling skips the scoring)."""

    model: DriverModel
    params: Sequence[str] | None
    fixed: Mapping[str, float] | None
    num_particles: int
    prior: Any
    progress: Callable[[int, int], None] | None
    pointwise: bool


class EngineResult(NamedTuple):
    """What an engine hands to :func:`build_tree` (numpy arrays; see the module docstring).

    posterior: parameter name -> (chain, draw, vehicle).
    sample_stats: name -> (dims, values) with dims among vehicle, step, param, epoch, ...
    log_likelihood: (chain, draw, vehicle, step), every posterior draw scored on every padded step
    (values on masked steps are dropped by :func:`build_tree`); None without ``pointwise``.
    compile_time_s: time spent compiling; wall_time_s: the inference itself, compilation excluded.
    options: the engine's settings, recorded in the metadata.
    prior: parameter name -> (chain, draw, vehicle) prior draws, where the engine makes them.
    """

    posterior: dict[str, np.ndarray]
    sample_stats: dict[str, tuple[tuple[str, ...], np.ndarray]]
    log_likelihood: np.ndarray | None
    compile_time_s: float
    wall_time_s: float
    options: dict[str, Any]
    prior: dict[str, np.ndarray] | None = None


def thinned_draws(num_draws: int, num_scored: int) -> np.ndarray:
    """Indices of ``num_scored`` evenly spaced draws out of ``num_draws`` (all when fewer)."""
    num_scored = min(num_scored, num_draws)
    return (np.arange(num_scored) * num_draws) // num_scored


def _draws_dataset(
    draws: Mapping[str, np.ndarray], vehicles: list[str], specs: Sequence[ParamSpec], what: str
) -> xr.Dataset:
    """Parameter draws (chain, draw, vehicle) as a dataset, each with its spec's unit and name."""
    first = np.shape(next(iter(draws.values())))
    for name, values in draws.items():
        if np.shape(values) != (*first[:2], len(vehicles)):
            raise ValueError(
                f"{what} {name!r} has shape {np.shape(values)}, expected "
                f"(chain, draw, vehicle) = ({first[0]}, {first[1]}, {len(vehicles)})"
            )
    described = {s.name: {"units": s.unit, "long_name": s.doc} for s in specs}
    return xr.Dataset(
        {
            name: xr.Variable(("chain", "draw", "vehicle"), np.asarray(v), described.get(name, {}))
            for name, v in draws.items()
        },
        coords={"chain": np.arange(first[0]), "draw": np.arange(first[1]), "vehicle": vehicles},
    )


def _observations(log_likelihood: np.ndarray, arrays: FollowerArrays) -> xr.Dataset:
    """The padded (chain, draw, vehicle, step) scores at the usable steps with a full history
    only: (chain, draw, obs)."""
    vehicle, step = np.nonzero(arrays.full_history_mask)
    scores = np.asarray(log_likelihood)
    # A vehicle at a time: the engines' scores are vehicle-major underneath (a moved-axis view),
    # so each vehicle's (chain, draw, step) block is contiguous and gathered in place. Reshaping
    # the whole view first copied every padded score into draw-major order, then gathered.
    values = np.empty((*scores.shape[:2], len(vehicle)), np.float32)
    bounds = np.searchsorted(vehicle, np.arange(scores.shape[2] + 1))
    for v, (start, stop) in enumerate(itertools.pairwise(bounds)):
        values[:, :, start:stop] = scores[:, :, v, step[start:stop]]
    return xr.Dataset(
        {OBSERVED_VARIABLE: (("chain", "draw", "obs"), values)},
        coords={
            "chain": np.arange(values.shape[0]),
            "draw": np.arange(values.shape[1]),
            "obs": np.arange(len(vehicle)),
            "vehicle": ("obs", np.asarray(arrays.vehicle_ids, dtype=str)[vehicle]),
            "step": ("obs", step),
            "t": ("obs", np.asarray(arrays.t)[vehicle, step], {"units": "s"}),
        },
    )


def _named(vehicles: Sequence[str]) -> str:
    shown = ", ".join(vehicles[:_NAMED_VEHICLES])
    rest = len(vehicles) - _NAMED_VEHICLES
    return shown + (f" and {rest} more" if rest > 0 else "")


def psis_loo_check(tree: xr.DataTree, *, markov_chains: bool) -> dict[str, Any]:
    """Whether ``arviz.loo`` can be trusted on ``tree``: ``reliable``, the ``problems`` found (one
    line each) and, where there are any, what to use ``instead`` (:data:`PSIS_ALTERNATIVE`).

    Two problems are looked for. Copies among the draws of a vehicle, where the draws are not
    ``markov_chains`` (resampled particles, Laplace draws clipped to the prior box, resampled
    two-stage draws): PSIS takes every draw as an independent one, so copies make its Pareto k
    and elpd unreliable (repeats in a Markov chain are rejections, which ArviZ's relative
    efficiency accounts for). And observations scored the same under every draw: PSIS cannot fit
    their tail, and ``arviz.loo`` raises. A result without the group (``pointwise=False``) is not
    checked: there is nothing to compute PSIS-LOO from.
    """
    if "log_likelihood" not in tree.children:
        return {
            "reliable": False,
            "problems": ["no log_likelihood group: fitted with pointwise=False"],
            "instead": "refit with the pointwise log-likelihood (the default)",
        }
    problems = []
    if not markov_chains:
        posterior = tree["posterior"].to_dataset()
        draws = np.stack(
            [
                posterior[n].transpose("chain", "draw", "vehicle").values
                for n in posterior.data_vars
            ],
            axis=-1,
        )
        draws = draws.reshape(-1, *draws.shape[2:])  # (draw, vehicle, param)
        distinct = [len(np.unique(draws[:, i], axis=0)) for i in range(draws.shape[1])]
        copied = [i for i, n in enumerate(distinct) if n < draws.shape[0]]
        if copied:
            fewest = min(copied, key=lambda i: distinct[i])
            vehicles = [str(posterior["vehicle"].values[i]) for i in copied]
            problems.append(
                f"{len(copied)} vehicle(s) hold copies among their {draws.shape[0]} draws "
                f"(fewest distinct: {distinct[fewest]}, vehicle {vehicles[copied.index(fewest)]}; "
                f"vehicles {_named(vehicles)}): PSIS takes every draw as independent, so its "
                "Pareto k and elpd are unreliable"
            )
    scores = tree["log_likelihood"][OBSERVED_VARIABLE]
    values = scores.transpose("chain", "draw", "obs").values
    constant = np.all(values == values[:1, :1], axis=(0, 1))
    if constant.any():
        vehicles = list(dict.fromkeys(str(v) for v in scores["vehicle"].values[constant]))
        problems.append(
            f"{int(constant.sum())} observation(s) score the same under every draw "
            f"(vehicles {_named(vehicles)}): PSIS cannot fit their tail and arviz.loo raises"
        )
    if problems:
        log.warning("PSIS-LOO cannot be trusted on this result: %s", "; ".join(problems))
    return {
        "reliable": not problems,
        "problems": problems,
        **({"instead": PSIS_ALTERNATIVE} if problems else {}),
    }


def _version(name: str) -> str:
    try:
        return version(name)
    except PackageNotFoundError:
        return "unknown"


def build_tree(
    *,
    posterior: Mapping[str, np.ndarray],
    sample_stats: Mapping[str, tuple[tuple[str, ...], np.ndarray]],
    log_likelihood: np.ndarray | None,
    arrays: FollowerArrays,
    metadata: Mapping[str, Any],
    specs: Sequence[ParamSpec] = (),
    prior: Mapping[str, np.ndarray] | None = None,
    inference_library: str = "bayesdrive",
    markov_chains: bool = False,
) -> xr.DataTree:
    """Assemble the result tree; ``metadata`` needs :data:`REQUIRED_METADATA` (versions, creation
    time, the split rule, the chain and draw counts and ``psis_loo`` are added here). ``specs``
    give the posterior's units and long names; ``inference_library`` names the package that drew
    the samples (a distribution name, for its version); ``markov_chains``: whether the draws are
    Markov chains, whose repeats are rejections, not copies (:func:`psis_loo_check`)."""
    missing = [k for k in REQUIRED_METADATA if k not in metadata]
    if missing:
        raise ValueError(f"result metadata lacks {missing}")
    num_vehicles, num_steps = arrays.mask.shape
    vehicles = list(arrays.vehicle_ids)
    posterior_ds = _draws_dataset(posterior, vehicles, specs, "posterior")
    num_chains, num_draws = posterior_ds.sizes["chain"], posterior_ds.sizes["draw"]
    expected = (num_chains, num_draws, num_vehicles, num_steps)
    if log_likelihood is not None and np.shape(log_likelihood) != expected:
        raise ValueError(
            f"log_likelihood has shape {np.shape(log_likelihood)}, expected every posterior draw "
            f"on every padded step: (chain, draw, vehicle, step) = {expected}"
        )

    stats_ds = xr.Dataset(
        {name: (dims, np.asarray(values)) for name, (dims, values) in sample_stats.items()}
    )
    coords = {"vehicle": vehicles, "step": np.arange(num_steps), "param": list(metadata["params"])}
    stats_ds = stats_ds.assign_coords({d: c for d, c in coords.items() if d in stats_ds.dims})

    observed_ds = xr.Dataset(
        {
            name: (("vehicle", "step"), np.asarray(getattr(arrays, name)))
            for name in ("t", "v", "next_v", "dx", "gap", "lead_v", "has_leader", "mask")
        },
        coords={"vehicle": vehicles, "step": coords["step"]},
        attrs={"dt": float(arrays.dt)},
    )

    groups = {"posterior": posterior_ds, "sample_stats": stats_ds}
    if log_likelihood is not None:
        groups["log_likelihood"] = _observations(log_likelihood, arrays)
    groups["observed_data"] = observed_ds
    if prior is not None:
        groups["prior"] = _draws_dataset(prior, vehicles, specs, "prior")
    provenance = {
        "inference_library": inference_library,
        "inference_library_version": _version(inference_library),
    }
    for name in _DRAW_GROUPS:
        if name in groups:
            groups[name].attrs.update(provenance)

    attrs = {
        **metadata,
        "num_chains": num_chains,
        "num_draws": num_chains * num_draws,
        "split_rule": SPLIT_RULE,
        "versions": {name: _version(name) for name in _VERSIONED},
        "code": code_provenance(),
        "created_at": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    tree = xr.DataTree.from_dict(groups)
    tree.attrs = _encode_attrs(
        {**attrs, "psis_loo": psis_loo_check(tree, markov_chains=markov_chains)}
    )
    return tree


def _encode_attrs(attrs: Mapping[str, Any]) -> dict[str, Any]:
    encoded, as_json = {}, []
    for key, value in attrs.items():
        # A loaded result's numbers are numpy scalars (netCDF): stored as the plain numbers.
        value = value.item() if isinstance(value, np.generic) else value
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


def set_metadata(tree: xr.DataTree, **values: Any) -> None:
    """Add or replace root metadata entries (encoded as :func:`build_tree` encodes them)."""
    tree.attrs = _encode_attrs({**metadata(tree), **values})


def save_result(tree: xr.DataTree, path: str | Path) -> Path:
    """Write the tree as netCDF (h5netcdf) atomically: a crash leaves no partial file."""
    path = Path(path)
    write_atomic(path, lambda tmp: tree.to_netcdf(tmp, engine="h5netcdf"))
    return path


def load_result(path: str | Path) -> xr.DataTree:
    """Read a saved result fully into memory (the file is closed again); a result of the older
    layout is converted to the current one, with a logged note of what changed."""
    path = Path(path)
    tree = xr.load_datatree(path, engine="h5netcdf")
    return _upgrade(tree, path)


def _upgrade(tree: xr.DataTree, path: Path) -> xr.DataTree:
    """Older results: log-likelihood padded to (vehicle, step) and thinned, or flat on every usable
    step (steps without a full history included), filters' ``ess``. Slim files without a
    log-likelihood (the posterior-only model cards) are returned as read."""
    if "log_likelihood" not in tree.children:
        return tree
    log_lik = tree["log_likelihood"].to_dataset()
    known = "obs" in log_lik.dims or "step" in log_lik.dims
    if not known or "observed_data" not in tree.children:
        if "obs" in log_lik.dims:
            return tree
        raise ValueError(
            f"{path}: unknown log_likelihood layout {dict(log_lik.sizes)} (expected dims chain, "
            "draw, obs, or the older chain, draw, vehicle, step beside observed_data)"
        )
    observed = tree["observed_data"].to_dataset()
    scored = full_history_mask(observed["mask"].values, history_steps(observed.attrs["dt"]))
    notes = []
    if "obs" in log_lik.dims:
        row_of = {str(v): i for i, v in enumerate(observed["vehicle"].values)}
        rows = np.array([row_of[str(v)] for v in log_lik["vehicle"].values], dtype=int)
        kept = scored[rows, log_lik["step"].values]
        if kept.all():
            return tree
        flat = log_lik[OBSERVED_VARIABLE].transpose("chain", "draw", "obs").values[:, :, kept]
        vehicle, step = rows[kept], log_lik["step"].values[kept]
        notes.append(
            f"log_likelihood cut to the {int(kept.sum())} of its {len(kept)} steps that have a "
            "full history (the steps every model scores)"
        )
    else:
        vehicle, step = np.nonzero(scored)
        flat = log_lik[OBSERVED_VARIABLE].values[:, :, vehicle, step]
        notes.append(f"log_likelihood flattened to the {len(vehicle)} steps with a full history")
    upgraded = xr.Dataset(
        {OBSERVED_VARIABLE: (("chain", "draw", "obs"), flat.astype(np.float32))},
        coords={
            "chain": log_lik["chain"].values,
            "draw": log_lik["draw"].values,
            "obs": np.arange(len(vehicle)),
            "vehicle": ("obs", observed["vehicle"].values.astype(str)[vehicle]),
            "step": ("obs", step),
            "t": ("obs", observed["t"].values[vehicle, step], {"units": "s"}),
        },
    )
    if log_lik.sizes["draw"] != tree["posterior"].sizes["draw"]:
        notes.append(
            f"it scores {log_lik.sizes['draw']} of the posterior's "
            f"{tree['posterior'].sizes['draw']} draws per chain (refit for PSIS-LOO on all)"
        )
    tree["log_likelihood"] = xr.DataTree(upgraded)
    stats = tree["sample_stats"].to_dataset()
    if "ess" in stats and "step" in stats["ess"].dims:
        tree["sample_stats"] = xr.DataTree(stats.rename({"ess": "particle_ess"}))
        notes.append("sample_stats.ess renamed particle_ess")
    log.warning("%s has the older result layout; converted in memory: %s", path, "; ".join(notes))
    return tree
