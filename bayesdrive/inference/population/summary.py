r"""Driver populations summarised: how parameters vary from driver to driver.

Two views, both from the same prior box and likelihood as every engine: (a) below, and (b) the
hierarchical model (:mod:`bayesdrive.inference.population.hierarchical`).

(a) **Pooled mixture** (the paper's population): every vehicle's posterior draws pooled into one
sample, each vehicle weighted equally (:func:`pooled_population`). It mixes between-driver spread
with each vehicle's own posterior uncertainty, so it is wider than the population whenever single
vehicles are poorly identified.

:func:`how_drivers_differ` summarises either view per parameter: the population's median and
10-90% range in natural units, the between-driver spread against the typical within-driver
posterior sd, and the pooled mixture's range for comparison.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import xarray as xr

__all__ = ["how_drivers_differ", "pooled_population"]


def pooled_population(posterior: xr.Dataset | Mapping[str, Any]) -> dict[str, np.ndarray]:
    """The paper's pooled mixture: each parameter's draws of all vehicles in one flat sample.

    Every vehicle has the same number of draws in a result, so pooling weights vehicles equally.
    """
    return {
        name: np.asarray(values).reshape(-1)
        for name, values in posterior.items()
        if np.ndim(values) == 3
    }


def how_drivers_differ(tree: xr.DataTree) -> dict[str, dict[str, Any]]:
    """Per parameter: population median and 10-90% range, between- vs within-driver spread.

    ``within_sd`` is the median over vehicles of each vehicle's posterior sd; ``between_sd`` is
    the sd of the population distribution (the hierarchical engine's ``population_new_driver``
    draws when the result has them, else the vehicles' posterior means). ``pooled_q10``/``pooled_q90``
    give the paper's pooled mixture for comparison.
    """
    posterior = tree["posterior"].to_dataset()
    pooled = pooled_population(posterior)
    stats = tree["sample_stats"].to_dataset() if "sample_stats" in tree.children else None
    has_population = stats is not None and "population_mu" in stats
    out: dict[str, dict[str, Any]] = {}
    for name in posterior.data_vars:
        draws = posterior[name]
        within = draws.std(("chain", "draw"))
        row: dict[str, Any] = {
            "within_sd": float(within.median()),
            "pooled_q10": float(np.quantile(pooled[name], 0.1)),
            "pooled_q90": float(np.quantile(pooled[name], 0.9)),
        }
        if has_population:
            population = stats.sel(param=name)
            new_driver = population["population_new_driver"].values.reshape(-1)
            median = population["population_median"].values.reshape(-1)
            tau = population["population_tau"].values.reshape(-1)
            row |= {
                "source": "hierarchical",
                "median": float(np.mean(median)),
                "median_q05": float(np.quantile(median, 0.05)),
                "median_q95": float(np.quantile(median, 0.95)),
                "q10": float(np.quantile(new_driver, 0.1)),
                "q90": float(np.quantile(new_driver, 0.9)),
                "between_sd": float(np.std(new_driver)),
                "tau_pop": float(np.mean(tau)),
                "tau_pop_q05": float(np.quantile(tau, 0.05)),
                "tau_pop_q95": float(np.quantile(tau, 0.95)),
            }
        else:
            means = draws.mean(("chain", "draw")).values
            row |= {
                "source": "vehicle posterior means",
                "median": float(np.median(means)),
                "q10": float(np.quantile(means, 0.1)),
                "q90": float(np.quantile(means, 0.9)),
                "between_sd": float(np.std(means)),
            }
        # Above 1: drivers differ by more than one driver's posterior can resolve.
        row["between_over_within"] = row["between_sd"] / row["within_sd"]
        out[name] = row
    return out
