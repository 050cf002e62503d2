"""The flat Python API, ``import bayesdrive as bd``: data in, a fit, its summary, simulations.

Thin entry points over the library, with the names and defaults a user of pandas and ArviZ
expects; each says which library function does the work. ``bayesdrive/__init__.py`` loads this
module on first use of any of its names, so ``import bayesdrive`` stays cheap.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd
import xarray as xr
from jax import Array

from bayesdrive import API
from bayesdrive.criticism.criticize import CriticismResult, CriticizeConfig
from bayesdrive.criticism.criticize import criticize as _criticize
from bayesdrive.data import registry
from bayesdrive.data.readers.columns import read_dataframe
from bayesdrive.data.trajectories import Trajectories
from bayesdrive.drivers.base import DriverModel
from bayesdrive.drivers.registry import MODELS, get_model
from bayesdrive.inference import fit as _fit

# Re-exported as they are (``name as name``: bayesdrive.API lists them).
from bayesdrive.inference.core.output import load_result as load_result
from bayesdrive.inference.core.output import save_result as save_result
from bayesdrive.simulation.evaluation import evaluate as evaluate
from bayesdrive.simulation.posterior import posterior_predictive as posterior_predictive
from bayesdrive.simulation.scenarios import fit_input

# The names are listed once, in the package, which loads this module on first use of one.
__all__ = list(API)

models = MODELS
load = registry.load_any
data_path = registry.resolve


def from_dataframe(
    frame: pd.DataFrame,
    columns: Mapping[str, str],
    *,
    units: str | float,
    mode: str = "pairs",
    **options: Any,
) -> Trajectories:
    """Trajectories from a pandas DataFrame, read as the column-map reader reads a CSV
    (:func:`~bayesdrive.data.readers.columns.read_dataframe`).

    ``columns`` maps the schema's names to the frame's columns: for ``mode="pairs"`` (one row per
    leader-follower pair and time) ``t``, ``x_follower``, ``v_follower``, ``x_leader``,
    ``v_leader`` and optionally ``follower_id``, ``leader_id``, ...; for ``mode="vehicles"`` (one
    row per vehicle and time, platoons linked by ``leader_id``) ``vehicle_id``, ``t``, ``x``,
    ``v``, .... ``units`` ("m", "ft" or a factor to metres) is required: nothing guesses units.
    Positions are front bumpers unless ``position="centre"`` or ``"rear"``.
    """
    return read_dataframe(frame, columns, mode=mode, units=units, **options)


def fit(
    key: Array,
    data: Trajectories | str | Path,
    *,
    model: str | DriverModel = "idm",
    engine: str = "smc",
    params: Sequence[str] | None = None,
    particles: int = 1000,
    vehicles: int | None = None,
    window: str = "fit",
    seed: int | None = None,
    data_dir: str | Path | None = None,
    **engine_options: Any,
) -> xr.DataTree:
    """Per-vehicle posteriors of ``model``'s ``params`` (default: all) from ``data``, as
    ``bayesdrive fit`` computes them (:func:`bayesdrive.inference.fit.fit`).

    ``data`` is trajectories or a data set name or path (read with :func:`load`, held-out names
    included, as ``bayesdrive fit`` reads them); merge episodes
    are fitted per stay of the cooperating car behind the merging car. ``vehicles`` keeps the first
    N vehicles with usable steps. ``seed`` is recorded beside the key's data. Returns the ArviZ
    DataTree that :func:`save_result` writes and :func:`load_result` reads.
    """
    driver = get_model(model) if isinstance(model, str) else model
    traj = data if isinstance(data, Trajectories) else load(data, data_dir=data_dir)
    return _fit.fit(
        key,
        fit_input(traj, window),
        source=traj.source,
        model=driver,
        engine=engine,
        params=params,
        num_particles=particles,
        window=window,
        seed=seed,
        max_vehicles=vehicles,
        **engine_options,
    )


def summary(result: xr.DataTree) -> pd.DataFrame:
    """One row per vehicle and parameter: its unit and the posterior's mean, sd and 5% and 95%
    quantiles (the figures of summary.json, :func:`bayesdrive.inference.fit.summary`)."""
    figures = _fit.summary(result)
    units = {spec.name: spec.unit for spec in get_model(figures["model"]).specs}
    rows = [
        {"vehicle": vehicle, "parameter": name, "unit": units[name], **described}
        for vehicle, by_param in figures["vehicles"].items()
        for name, described in by_param.items()
    ]
    return pd.DataFrame(rows).set_index(["vehicle", "parameter"])


def criticize(
    data: Trajectories | str | Path,
    *,
    seed: int,
    model: str = "idm",
    vehicles: int | None = None,
    data_dir: str | Path | None = None,
    **config: Any,
) -> CriticismResult:
    """What the base ``model`` gets wrong on ``data`` and which extension fixes it, as
    ``bayesdrive criticize`` finds it (:func:`bayesdrive.criticism.criticize.criticize`).

    ``vehicles`` keeps the first N scored vehicles (as :func:`fit` counts them); ``config`` sets
    fields of :class:`~bayesdrive.criticism.criticize.CriticizeConfig` (e.g. ``num_particles``,
    ``num_rollouts``, ``causes``). The report (``.report``) is JSON-ready; its ``power_warning``
    says when too few vehicles give the checks no power.
    """
    # Not load: the criticism chooses a model, which a held-out set must never decide.
    traj = data if isinstance(data, Trajectories) else registry.load(data, data_dir=data_dir)
    return _criticize(
        traj,
        seed=seed,
        model=get_model(model),
        config=CriticizeConfig(**config),
        max_vehicles=vehicles,
    )
