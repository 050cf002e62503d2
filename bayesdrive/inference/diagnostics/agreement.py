r"""Convergence diagnostics of one result and agreement between results of different engines.

**Convergence** (:func:`convergence_table`), per vehicle and parameter, through ArviZ 1.x:
rank-normalised split R-hat (only with two or more chains: the walkers of one emcee ensemble and
the particles of a filter are not independent chains, so no R-hat is reported for them), bulk and
tail effective sample size and the Monte Carlo standard errors of the mean and the sd
(:func:`mcse_mean`, :func:`mcse_sd`). Within a single chain ESS and MCSE come from the
autocorrelation along the stored draw order. Engine
extras are joined where the result has them: NUTS divergences per vehicle, emcee's integrated
autocorrelation time (its maximum over parameters, the thinning) and whether the run was longer
than 50 of them.

**Agreement** (:func:`agreement_table`), for every pair (a, b) of results on the same data, per
vehicle and parameter, with :math:`s = \sqrt{(sd_a^2 + sd_b^2)/2}`:

* ``mean_diff_sd`` = :math:`(\bar\theta_b - \bar\theta_a)/s`, the difference of posterior means in
  posterior sds;
* ``sd_ratio`` = :math:`sd_b / sd_a`;
* ``wasserstein`` = the 1-Wasserstein distance between the two sets of draws
  (``scipy.stats.wasserstein_distance``), also in units of s (``wasserstein_sd``);
* ``mc_tolerance`` = :math:`3\sqrt{mcse_a^2 + mcse_b^2}`, what Monte Carlo error alone explains
  in the means, and ``sd_mc_tolerance`` the same for the sds, from their own Monte Carlo
  standard errors;
* ``agree`` = :math:`|\bar\theta_b - \bar\theta_a| \le \max(0.1\,s,\ \text{mc\_tolerance})` and
  :math:`|sd_b - sd_a| \le \max(0.1 \min(sd_a, sd_b),\ \text{sd\_mc\_tolerance})`: the sds within
  10%, or within what Monte Carlo error explains. The sd's Monte Carlo error grows with the
  marginal's kurtosis: between two exact samplers of 1000 independent draws each, sds of a
  skewed or heavy-tailed marginal differ by more than 10% often (``tests/inference/test_agreement.py``).

**Exact reference** (:func:`grid_posterior`): with one inferred parameter the posterior is a
1-D integral, computed by quadrature on a fine grid over the prior interval, the answer every
engine must reproduce up to Monte Carlo error.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import scipy.stats
import xarray as xr

from bayesdrive.data.views import FollowerArrays
from bayesdrive.drivers.base import DriverModel
from bayesdrive.inference.core.likelihood import fixed_params, series_loglik, step_inputs
from bayesdrive.inference.core.output import metadata

__all__ = [
    "CRITERION",
    "MC_TOLERANCE_SE",
    "MEAN_TOLERANCE_SD",
    "SD_TOLERANCE",
    "agreement_summary",
    "agreement_table",
    "convergence_table",
    "grid_posterior",
    "judge",
    "mcse_mean",
    "mcse_sd",
    "same_data",
]

MEAN_TOLERANCE_SD = 0.1
MC_TOLERANCE_SE = 3.0
SD_TOLERANCE = 0.1
CRITERION = (
    f"|mean_b - mean_a| <= max({MEAN_TOLERANCE_SD} * pooled sd, {MC_TOLERANCE_SE} * "
    f"sqrt(mcse_a^2 + mcse_b^2)) and |sd_b - sd_a| <= max({SD_TOLERANCE} * min(sd), "
    f"{MC_TOLERANCE_SE} * sqrt(mcse_sd_a^2 + mcse_sd_b^2))"
)


class Verdict(NamedTuple):
    """The criterion on one parameter of two runs: the pooled sd s, the Monte Carlo part of the
    tolerance, the tolerance on the means' difference, the same two for the sds, and whether
    means and sds agree."""

    pooled_sd: float
    mc_tolerance: float
    tolerance: float
    sd_mc_tolerance: float
    sd_tolerance: float
    agree_mean: bool
    agree_sd: bool


def judge(
    mean_a: float,
    sd_a: float,
    mcse_a: float,
    mean_b: float,
    sd_b: float,
    mcse_b: float,
    *,
    mcse_sd_a: float,
    mcse_sd_b: float,
) -> Verdict:
    """:data:`CRITERION` for one parameter of runs a and b (module docstring): ``mcse_*`` the
    Monte Carlo standard errors of the means, ``mcse_sd_*`` of the sds."""
    pooled_sd = float(np.sqrt((sd_a**2 + sd_b**2) / 2.0))
    mc_tolerance = MC_TOLERANCE_SE * float(np.hypot(mcse_a, mcse_b))
    tolerance = max(MEAN_TOLERANCE_SD * pooled_sd, mc_tolerance)
    sd_mc_tolerance = MC_TOLERANCE_SE * float(np.hypot(mcse_sd_a, mcse_sd_b))
    sd_tolerance = max(SD_TOLERANCE * min(sd_a, sd_b), sd_mc_tolerance)
    return Verdict(
        pooled_sd=pooled_sd,
        mc_tolerance=mc_tolerance,
        tolerance=tolerance,
        sd_mc_tolerance=sd_mc_tolerance,
        sd_tolerance=sd_tolerance,
        agree_mean=bool(abs(mean_b - mean_a) <= tolerance),
        agree_sd=bool(abs(sd_b - sd_a) <= sd_tolerance),
    )


def _posterior(tree: xr.DataTree) -> xr.Dataset:
    return tree["posterior"].to_dataset()


def _per_vehicle(values: xr.DataTree | xr.Dataset, name: str) -> np.ndarray:
    dataset = values.to_dataset() if isinstance(values, xr.DataTree) else values
    return np.asarray(dataset[name].values, dtype=np.float64)


def mcse_mean(tree: xr.DataTree) -> xr.Dataset:
    """Monte Carlo standard error of each posterior mean [vehicle].

    For a result whose chains are independent replicate runs (``engine_options.replicates`` > 1,
    smc) it is the spread of the replicate means, sd / sqrt(R): draws within one SMC run are
    correlated through resampling in a way no autocorrelation along the draw order captures.
    Otherwise ArviZ's estimate from the chains' autocorrelation.
    """
    return _mcse(tree, "mean")


def mcse_sd(tree: xr.DataTree) -> xr.Dataset:
    """Monte Carlo standard error of each posterior sd [vehicle], as :func:`mcse_mean` takes it
    (the spread of the replicate sds for replicate runs, else ArviZ's estimate)."""
    return _mcse(tree, "sd")


def _mcse(tree: xr.DataTree, statistic: str) -> xr.Dataset:
    replicates = metadata(tree).get("engine_options", {}).get("replicates", 1)
    if replicates > 1:
        draws = _posterior(tree)
        per_replicate = draws.mean("draw") if statistic == "mean" else draws.std("draw")
        return per_replicate.std("chain", ddof=1) / np.sqrt(replicates)
    import arviz  # here, not at the top: a fit whose checks need no ArviZ does not import it

    return arviz.mcse(tree, method=statistic).to_dataset()


def convergence_table(tree: xr.DataTree, *, statistics: bool = True) -> pd.DataFrame:
    """One row per vehicle and parameter: R-hat (NaN with one chain), ESS, MCSE, engine extras.

    ``statistics=False`` gives the draws' sd and the engine extras only: the ESS and MCSE
    estimators cost seconds per hundred vehicles, and a caller with no check to run on them
    (one-chain filters) need not pay for them."""
    posterior = _posterior(tree)
    names = list(posterior.data_vars)
    multi_chain = posterior.sizes["chain"] >= 2
    stats = {}
    if statistics:
        import arviz  # here, not at the top: one-chain filters need no ArviZ

        stats = {
            "ess_bulk": arviz.ess(tree, method="bulk"),
            "ess_tail": arviz.ess(tree, method="tail"),
            "mcse_mean": mcse_mean(tree),
            "mcse_sd": mcse_sd(tree),
        }
        if multi_chain:
            stats["rhat"] = arviz.rhat(tree)
    sample_stats = tree["sample_stats"].to_dataset() if "sample_stats" in tree.children else None
    vehicles = [str(v) for v in posterior["vehicle"].values]
    rows = []
    for k, name in enumerate(names):
        values = {key: _per_vehicle(result, name) for key, result in stats.items()}
        for i, vehicle in enumerate(vehicles):
            row = {"vehicle": vehicle, "param": name}
            if statistics:
                row["rhat"] = float(values["rhat"][i]) if multi_chain else float("nan")
                row |= {key: float(values[key][i]) for key in stats if key != "rhat"}
            row["sd"] = float(posterior[name].values[:, :, i].std())
            if statistics:
                # The ESS the mean's standard error implies (the replicate one for smc).
                # NaN where every draw is equal (sd and MCSE 0): no ESS to speak of.
                mcse = row["mcse_mean"]
                row["ess_mean"] = (row["sd"] / mcse) ** 2 if mcse > 0.0 else float("nan")
            if sample_stats is not None:
                row |= _engine_extras(sample_stats, i, k)
            rows.append(row)
    return pd.DataFrame(rows)


def _engine_extras(sample_stats: xr.Dataset, vehicle: int, param: int) -> dict[str, float]:
    """Divergences (NUTS) and autocorrelation times (emcee) for one vehicle, where present."""
    extras: dict[str, float] = {}
    if "diverging" in sample_stats and "vehicle" in sample_stats["diverging"].dims:
        extras["divergences"] = float(sample_stats["diverging"].isel(vehicle=vehicle).values.sum())
    if "autocorr_time" in sample_stats:
        extras["autocorr_time"] = float(
            sample_stats["autocorr_time"].isel(vehicle=vehicle).values[param]
        )
        extras["thin"] = float(sample_stats["thin"].isel(vehicle=vehicle))
        extras["autocorr_reliable"] = float(sample_stats["autocorr_reliable"].isel(vehicle=vehicle))
    return extras


def same_data(trees: Mapping[str, xr.DataTree]) -> None:
    """Refuse results fitted to different data: source, window and model must all match."""
    keys = ("data_source", "window", "model")
    seen = {label: tuple(metadata(tree).get(k) for k in keys) for label, tree in trees.items()}
    if len(set(seen.values())) > 1:
        detail = "; ".join(
            f"{label}: {dict(zip(keys, v, strict=True))}" for label, v in seen.items()
        )
        raise ValueError(f"results are not on the same data and model: {detail}")


def agreement_table(trees: Mapping[str, xr.DataTree]) -> pd.DataFrame:
    """Every pair of results, per shared vehicle and parameter (module docstring for columns).

    ``trees`` maps a label (e.g. the engine name) to a result. Only vehicles and parameters that
    all results share are compared; none shared is an error.
    """
    if len(trees) < 2:
        raise ValueError("agreement needs at least two results")
    posteriors = {label: _posterior(tree) for label, tree in trees.items()}
    mcse = {label: mcse_mean(tree) for label, tree in trees.items()}
    sd_mcse = {label: mcse_sd(tree) for label, tree in trees.items()}
    vehicle_sets = [set(map(str, p["vehicle"].values)) for p in posteriors.values()]
    param_sets = [set(p.data_vars) for p in posteriors.values()]
    first = next(iter(posteriors.values()))
    vehicles = [v for v in map(str, first["vehicle"].values) if all(v in s for s in vehicle_sets)]
    params = [n for n in first.data_vars if all(n in s for s in param_sets)]
    if not vehicles or not params:
        raise ValueError(
            f"the results share no vehicle and parameter (vehicles in common: {len(vehicles)}, "
            f"parameters in common: {params})"
        )

    def draws(label: str, name: str, vehicle: str) -> np.ndarray:
        values = posteriors[label][name].sel(vehicle=vehicle).values
        return np.asarray(values, dtype=np.float64).ravel()

    def standard_error(errors: Mapping[str, xr.Dataset], label: str, name: str, vehicle: str):
        return float(errors[label][name].sel(vehicle=vehicle))

    rows = []
    for a, b in itertools.combinations(trees, 2):
        for name in params:
            for vehicle in vehicles:
                draws_a, draws_b = draws(a, name, vehicle), draws(b, name, vehicle)
                mean_a, mean_b = draws_a.mean(), draws_b.mean()
                sd_a, sd_b = draws_a.std(), draws_b.std()
                mcse_a, mcse_b = (standard_error(mcse, x, name, vehicle) for x in (a, b))
                mcse_sd_a, mcse_sd_b = (standard_error(sd_mcse, x, name, vehicle) for x in (a, b))
                verdict = judge(
                    mean_a,
                    sd_a,
                    mcse_a,
                    mean_b,
                    sd_b,
                    mcse_b,
                    mcse_sd_a=mcse_sd_a,
                    mcse_sd_b=mcse_sd_b,
                )
                pooled_sd = verdict.pooled_sd
                distance = float(scipy.stats.wasserstein_distance(draws_a, draws_b))
                rows.append(
                    {
                        "a": a,
                        "b": b,
                        "vehicle": vehicle,
                        "param": name,
                        "mean_a": float(mean_a),
                        "mean_b": float(mean_b),
                        "sd_a": float(sd_a),
                        "sd_b": float(sd_b),
                        "mcse_a": mcse_a,
                        "mcse_b": mcse_b,
                        "mcse_sd_a": mcse_sd_a,
                        "mcse_sd_b": mcse_sd_b,
                        "mean_diff_sd": float((mean_b - mean_a) / pooled_sd),
                        "sd_ratio": float(sd_b / sd_a),
                        "wasserstein": distance,
                        "wasserstein_sd": distance / pooled_sd,
                        "mc_tolerance": verdict.mc_tolerance,
                        "sd_mc_tolerance": verdict.sd_mc_tolerance,
                        "agree_mean": verdict.agree_mean,
                        "agree_sd": verdict.agree_sd,
                        "agree": verdict.agree_mean and verdict.agree_sd,
                    }
                )
    return pd.DataFrame(rows)


def agreement_summary(table: pd.DataFrame) -> pd.DataFrame:
    """Per pair and parameter: share of vehicles agreeing and the worst departures."""
    grouped = table.groupby(["a", "b", "param"], sort=False)
    return grouped.agg(
        vehicles=("vehicle", "size"),
        agree=("agree", "mean"),
        agree_mean=("agree_mean", "mean"),
        agree_sd=("agree_sd", "mean"),
        max_abs_mean_diff_sd=("mean_diff_sd", lambda d: float(np.max(np.abs(d)))),
        median_sd_ratio=("sd_ratio", "median"),
        max_wasserstein_sd=("wasserstein_sd", "max"),
    ).reset_index()


def grid_posterior(
    arrays: FollowerArrays,
    model: DriverModel,
    name: str,
    *,
    vehicle: int = 0,
    fixed: Mapping[str, float] | None = None,
    points: int = 4001,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact posterior of one parameter of one vehicle on a grid: (grid, normalised density).

    Uniform prior on the model's bounds for ``name``, the others at ``fixed`` (else defaults);
    the likelihood is the engines' (:func:`~bayesdrive.inference.core.likelihood.series_loglik`),
    normalised by the trapezoid rule in float64.
    """
    spec = model.spec(name)
    grid = np.linspace(spec.lower, spec.upper, points)
    series = jax.tree.map(lambda a: a[vehicle], step_inputs(arrays, model))
    base = fixed_params(model, fixed)
    log_lik = jax.jit(
        jax.vmap(lambda th: series_loglik(model, (name,), base, th[None], series).sum())
    )(jnp.asarray(grid, dtype=float))
    log_lik = np.asarray(log_lik, dtype=np.float64)
    density = np.exp(log_lik - log_lik.max())
    return grid, density / np.trapezoid(density, grid)
