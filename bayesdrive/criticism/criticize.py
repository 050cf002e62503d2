"""Name the cause of a misfit: fit the base model, check it, fit the extensions the checks point to,
and keep the one whose held-out gain is largest, if it is significant.

Steps (``criticize``):

1. Build the per-step arrays with the history the extensions need
   (:func:`~bayesdrive.data.views.scored_series`; same split rule as every engine).
2. Fit the base model to every vehicle's fitting window and continue over its held-out window
   (:mod:`bayesdrive.inference.engines.heldout_evidence`).
3. Run the checks on the held-out windows (:mod:`bayesdrive.criticism.checks`), including
   closed-loop rollouts of the base model.
4. **Screening**: a cause is a candidate when one of the screening checks that point to it (score
   tests, per-vehicle autocorrelations and responses: p-values calibrated across vehicles) has
   p < 0.2
   (Bonferroni within the cause's checks); lenient on purpose, since the verdict is decided by the
   gain, whose multiplicity correction covers every cause whether screened in or not.
5. Fit each candidate extension, starting from the base posterior (the extension nests the base
   model; see :func:`~bayesdrive.inference.engines.heldout_evidence.fit_model`), continue it over the held-out
   window the same way, and compute its gain, significance (Holm over all causes) and rollout RMSE
   change (:mod:`bayesdrive.criticism.gain`).
6. Verdict: the significant cause with the largest gain, else "none".
7. **The loop.** With a verdict, the model is extended by it and the next round asks what the
   extended model still gets wrong: every cause screened in at step 4 that composes with it
   (:func:`~bayesdrive.drivers.extensions.composition_problem`) is added to it, fitted from its
   posterior, and its held-out gain over it tested as in step 5; the significant cause with the
   largest gain extends the model again, until a round finds none or ``max_rounds`` rounds ran.
   The residual checks describe the base model's misfit, so they run once; later rounds decide
   by the held-out (leave-future-out) gain alone.

**Multiplicity across rounds.** Each round tests its family (every cause that still composes,
unfitted ones counting as p = 1) with Holm at ``alpha``, and a round runs only after the round
before named a cause: a fixed-sequence gate, so on data where no cause helps the loop's
false-positive rate is the first round's, whatever ``max_rounds`` is.

Randomness: one seed; each part draws from its own key, derived from the seed by name
(``fold_in`` of a hash of the name), so adding a cause never changes another's draws. The rollouts
of every model share one key on purpose (common random numbers: the same noise and the same draw
indices), so RMSE differences between models are not swamped by simulation noise.

**Processing artefacts.** On real data a misfit can come from how the data were made rather than
from drivers: the NGSIM I-80 chains were EMD-smoothed (smoothing alone makes residuals
autocorrelated and lags the response), OpenACC positions were spline-interpolated from 3-5 Hz GNSS
(smooth between fixes, same effect). :data:`PROCESSING_ARTEFACTS` names, per reader format, the
causes such processing can fake; the report marks those findings.
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import numpy as np

from bayesdrive.criticism.checks import Check, Residuals, multistep_check, run_checks
from bayesdrive.criticism.gain import ALPHA, Gain, elpd_gain, holm, rmse_change
from bayesdrive.data.errors import DataError
from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.views import SPLIT_RULE, FollowerArrays, follower_arrays, scored_series
from bayesdrive.drivers.base import DriverModel
from bayesdrive.drivers.closed_loop import FILTERED, forecast_start
from bayesdrive.drivers.extensions import (
    CAUSES,
    NO_CAUSE,
    as_extended,
    compose,
    composition_problem,
    extend,
)
from bayesdrive.drivers.idm import IDM
from bayesdrive.inference.engines.heldout_evidence import DEFAULT_CONFIG, FitResult, fit_model
from bayesdrive.simulation.follower_rollout import Rollouts, heldout_windows, rollout

__all__ = [
    "DETECTION_CONFIG",
    "PROCESSING_ARTEFACTS",
    "SCREEN_P",
    "CriticismResult",
    "CriticizeConfig",
    "criticize",
    "criticized_series",
    "named_key",
    "power_warning",
]

SCREEN_P = 0.2
# The detection study (reports/criticism/detection.md) showed the checks' and the gain test's power
# with this many vehicles; fewer is untested ground.
# The detection study's vehicle count (two platoons of four followers: DETECTION_SCENARIO of the
# independent generator, which the library cannot import; tests/cli/test_criticism_cli.py ties the two).
POWERED_VEHICLES = 8
SMOOTHING = (
    "the trajectories were smoothed, which alone makes residuals autocorrelated and lags the "
    "apparent response"
)
PROCESSING_ARTEFACTS: dict[str, dict[str, str]] = {
    "ngsim_chains": {
        "autocorrelated_noise": f"EMD-smoothed NGSIM chains: {SMOOTHING}",
        "reaction_delay": f"EMD-smoothed NGSIM chains: {SMOOTHING}",
        "drifting_parameters": f"EMD-smoothed NGSIM chains: {SMOOTHING}",
    },
    "openacc": {
        "autocorrelated_noise": "OpenACC positions are splines through 3-5 Hz GNSS fixes: "
        "residuals between fixes are correlated by construction",
        "reaction_delay": "OpenACC positions are splines through 3-5 Hz GNSS fixes: "
        "interpolation can shift the apparent timing of responses",
        "measurement_noise": "OpenACC: GNSS position error is real measurement noise, but the "
        "spline interpolation changes its structure",
    },
}


class CriticizeConfig(NamedTuple):
    """Settings of a criticism run; ``causes`` is the family of causes considered."""

    num_particles: int = DEFAULT_CONFIG.num_particles
    num_moves: int = DEFAULT_CONFIG.num_moves
    # Moves per tempering stage continue past num_moves until a particle has moved with
    # probability 1 - this (bayesdrive.inference.engines.heldout_evidence, "How many moves"); 0: num_moves only.
    unmoved_tolerance: float = DEFAULT_CONFIG.unmoved_tolerance
    screen_p: float = SCREEN_P
    alpha: float = ALPHA
    horizon_s: float = 5.0
    num_rollouts: int = 32  # per held-out window; 0 skips the rollouts (no RMSE, no multistep)
    causes: tuple[str, ...] = CAUSES
    vehicle_batch: int = 1  # see bayesdrive.inference.engines.heldout_evidence.fit_model
    max_rounds: int = 3  # rounds of the loop (module docstring, step 7); 1: the first cause only


# Settings of the detection study and of the CI tests built on it (see DETECTION_SCENARIO in
# trafficgen, the independent generator at the repository root): the default sampler (moves until every particle has moved with
# probability 0.99, Drovandi & Pettitt 2011's c = 0.01, since 4 fixed moves let the speed-noise
# posterior collapse: bayesdrive.inference.engines.heldout_evidence), without rollouts, to keep CI fast.
DETECTION_CONFIG = CriticizeConfig(num_rollouts=0)


class CriticismResult(NamedTuple):
    """The JSON-ready report plus what the pictures need (``fits``, ``gains`` and ``rollouts``
    of the first round, by cause; ``final`` the fit of the final model on the fitting windows and
    its rollouts)."""

    report: dict[str, Any]
    checks: list[Check]
    residuals: Residuals
    series: FollowerArrays
    fits: dict[str, FitResult]
    gains: dict[str, Gain]
    rollouts: dict[str, Rollouts]
    final: FitResult


def named_key(key: jax.Array, name: str) -> jax.Array:
    """A key for one named part of the run, independent of which other parts exist."""
    return jax.random.fold_in(key, zlib.crc32(name.encode()) & 0x7FFFFFFF)


def _screen(checks: Sequence[Check], cause: str, screen_p: float) -> tuple[bool, dict[str, Any]]:
    """Whether the screening checks point to ``cause`` (Bonferroni within them), and the evidence
    (every check that points to it, screening or descriptive)."""
    pointing = [c for c in checks if cause in c.points_to and c.p_value is not None]
    evidence = {
        c.name: {
            "statistic": c.statistic,
            "p_value": _directional_p(c, cause),
            "screening": c.screening,
        }
        for c in pointing
    }
    screening = [e["p_value"] for e in evidence.values() if e["screening"]]
    smallest = min(screening, default=1.0)
    return bool(screening) and smallest * len(screening) < screen_p, evidence


def _directional_p(check: Check, cause: str) -> float:
    """The p-value in the direction that points to ``cause`` where the check has one."""
    directional = {
        ("autocorrelation", "autocorrelated_noise"): "p_positive",
        ("autocorrelation", "measurement_noise"): "p_negative",
        ("autocorrelation", "drifting_parameters"): "p_long_lag",
        ("variance_vs_speed", "speed_dependent_noise"): "p_positive",
        ("lag1_by_vehicle", "measurement_noise"): "p_negative",
        ("lag1_by_vehicle", "drifting_parameters"): "p_positive",
    }
    field = directional.get((check.name, cause))
    return float(check.summary[field]) if field else float(check.p_value)


def _posterior_summary(fit: FitResult, names: Sequence[str]) -> dict[str, dict[str, float]]:
    """Across vehicles: mean of the per-vehicle posterior means, and their 5%/95% quantiles."""
    out = {}
    for name in names:
        means = fit.theta[:, :, fit.names.index(name)].mean(axis=1)
        out[name] = {
            "mean": float(means.mean()),
            "q05_vehicles": float(np.quantile(means, 0.05)),
            "q95_vehicles": float(np.quantile(means, 0.95)),
        }
    return out


def _gain_entry(gain: Gain, series: FollowerArrays, significant: bool) -> dict[str, Any]:
    """A gain as the JSON report states it."""
    return {
        "elpd": _finite_or_none(gain.elpd),
        "se": _finite_or_none(gain.se),
        "t": _finite_or_none(gain.t),
        "t_log_transformed": _finite_or_none(gain.t_transformed),
        "non_finite_vehicles": [
            series.vehicle_ids[i] for i in np.flatnonzero(~np.isfinite(gain.per_vehicle))
        ],
        "p_value": gain.p_value,
        "significant": significant,
        "vehicles_improved": int(np.sum(gain.per_vehicle > 0)),
    }


def composes(present: tuple[str, ...], cause: str) -> bool:
    """Whether ``cause`` can join a model that has the extensions ``present``."""
    return composition_problem((*present, cause)) is None


def _finite_or_none(value: float) -> float | None:
    """JSON has no NaN: a number that could not be computed is null."""
    return float(value) if np.isfinite(value) else None


def criticized_series(traj: Trajectories, max_vehicles: int | None = None) -> FollowerArrays:
    """The per-step arrays criticism scores: every follower with scored steps in both windows;
    with ``max_vehicles``, the first N of them in the order ``fit`` takes vehicles (its
    fitting-window followers), their leaders read from all of ``traj``."""
    if max_vehicles is None:
        return scored_series(traj)
    if max_vehicles < 1:
        raise ValueError(f"the number of vehicles must be positive, got {max_vehicles}")
    candidates = list(follower_arrays(traj, window="fit").vehicle_ids)
    taken = max_vehicles
    while True:
        # Some candidates lack held-out steps; take more until N are scored or none are left.
        try:
            series = scored_series(traj, vehicle_ids=candidates[:taken])
            found = len(series.vehicle_ids)
        except DataError:
            if taken >= len(candidates):
                raise
            found = 0
        if found >= max_vehicles or taken >= len(candidates):
            return series
        taken = min(len(candidates), taken + max_vehicles - found)


def power_warning(num_vehicles: int) -> str | None:
    """Why the checks and the gain test say little with ``num_vehicles`` vehicles, or None."""
    if num_vehicles >= POWERED_VEHICLES:
        return None
    test = (
        "the gain test (a t-test across vehicles) is undefined with one vehicle"
        if num_vehicles < 2
        else f"the gain test is a t-test across vehicles with {num_vehicles - 1} degree(s) of "
        "freedom"
    )
    return (
        f"only {num_vehicles} vehicle(s) criticized: {test}, and the checks are calibrated "
        f"across vehicles; their power was shown with {POWERED_VEHICLES} vehicles "
        "(reports/criticism/detection.md), so with fewer a verdict of 'none' means little: use "
        f"at least {POWERED_VEHICLES} vehicles"
    )


def criticize(
    traj: Trajectories,
    *,
    seed: int,
    model: DriverModel = IDM,
    config: CriticizeConfig = CriticizeConfig(),  # noqa: B008 - an immutable NamedTuple
    max_vehicles: int | None = None,
    progress: Callable[[str], None] | None = None,
    client: Any = None,
    chunk_size: int | None = None,
) -> CriticismResult:
    """Name the cause of the base model's misfit on ``traj`` (module docstring); with
    ``max_vehicles``, on its first N scored vehicles (:func:`criticized_series`). With a Dask
    ``client``, every fit runs in chunks of ``chunk_size`` vehicles on its cluster
    (:func:`~bayesdrive.inference.distributed.fit_model_on_cluster`): the same report."""
    unknown = [c for c in config.causes if c not in CAUSES]
    if unknown:
        raise KeyError(f"unknown cause(s) {unknown}; known: {list(CAUSES)}")
    if client is not None and config.vehicle_batch != 1:
        raise ValueError("on a cluster the criticism fits one vehicle at a time (vehicle_batch 1)")
    say = progress or (lambda message: None)
    key = jax.random.key(seed)
    fit_config = DEFAULT_CONFIG._replace(
        num_particles=config.num_particles,
        num_moves=config.num_moves,
        unmoved_tolerance=config.unmoved_tolerance,
    )
    started = time.perf_counter()

    series = criticized_series(traj, max_vehicles)
    windows = heldout_windows(series, config.horizon_s)
    if config.num_rollouts == 0:
        windows = windows._replace(row=windows.row[:0], start=windows.start[:0])
    rollout_key = named_key(key, "rollouts")

    def fit_and_roll(extended, start: FitResult | None) -> tuple[FitResult, Rollouts]:
        # Keys by the causes in the model, so round one's draws do not depend on later rounds.
        causes_in = "+".join((*present, extended.cause)) if present else extended.cause
        fit_key = named_key(key, f"fit:{causes_in}")
        if client is None:
            fit = fit_model(
                fit_key,
                series,
                extended,
                config=fit_config,
                start=start,
                vehicle_batch=config.vehicle_batch,
            )
        else:
            from bayesdrive.inference.distributed import DEFAULT_CHUNK_SIZE, fit_model_on_cluster

            fit = fit_model_on_cluster(
                client,
                fit_key,
                series,
                extended,
                config=fit_config,
                start=start,
                chunk_size=chunk_size or DEFAULT_CHUNK_SIZE,
            )
        start_of_rollouts = forecast_start(extended.model)
        if start_of_rollouts != FILTERED and windows.row.size:
            say(
                f"{extended.name}: rollouts start {start_of_rollouts} (its hidden state is not "
                "filtered by the simulator)"
            )
        rolled = rollout(
            rollout_key,
            extended,
            fit.theta,
            series,
            windows,
            num_rollouts=config.num_rollouts,
            start=start_of_rollouts,
        )
        return fit, rolled

    present: tuple[str, ...] = ()
    say(f"fitting the base model ({model.name}) to {len(series.vehicle_ids)} vehicles")
    base, base_rollouts = fit_and_roll(as_extended(model), None)
    say("running the checks")
    residuals, checks = run_checks(named_key(key, "checks"), base, series, causes=config.causes)
    checks.append(multistep_check(base_rollouts, series.dt))
    screening = {cause: _screen(checks, cause, config.screen_p) for cause in config.causes}
    screened = [cause for cause in config.causes if screening[cause][0]]
    artefacts = PROCESSING_ARTEFACTS.get(traj.format, {})
    num_vehicles = len(series.vehicle_ids)

    def one_round(current: FitResult, current_rollouts: Rollouts) -> dict[str, Any]:
        """Extend the current model by each composable screened cause; test the gains."""
        family = [c for c in config.causes if c not in present and composes(present, c)]
        fits: dict[str, FitResult] = {}
        rolled: dict[str, Rollouts] = {}
        gains: dict[str, Gain] = {}
        for cause in (c for c in screened if c in family):
            say(f"round {len(present) + 1}: fitting {extend(cause, model, present).name}")
            fits[cause], rolled[cause] = fit_and_roll(extend(cause, model, present), current)
            gains[cause] = elpd_gain(current, fits[cause])
        significant = holm({c: g.p_value for c, g in gains.items()}, family, config.alpha)
        ranked = sorted(
            gains,
            key=lambda c: gains[c].elpd if np.isfinite(gains[c].elpd) else -np.inf,
            reverse=True,
        )
        current_rmse = current_rollouts.rmse_per_vehicle(num_vehicles)
        entries = []
        for cause in [*ranked, *(c for c in family if c not in gains)]:
            extended = extend(cause, model, present)
            entry: dict[str, Any] = {
                "name": cause,
                "extension": extended.name,
                "new_params": list(extended.new_params),
                "screened_in": screening[cause][0],
                "evidence": screening[cause][1],
                "possible_processing_artefact": artefacts.get(cause),
                "gain": None,
            }
            if cause in gains:
                change, change_se = rmse_change(
                    current_rmse, rolled[cause].rmse_per_vehicle(num_vehicles)
                )
                entry["gain"] = _gain_entry(gains[cause], series, cause in significant)
                entry["gain"]["rmse_position_change"] = _finite_or_none(change)
                entry["gain"]["rmse_position_change_se"] = _finite_or_none(change_se)
                entry["gain"]["rollout_start"] = rolled[cause].start
                entry["posterior"] = _posterior_summary(fits[cause], extended.new_params)
            entries.append(entry)
        return {
            "verdict": next((c for c in ranked if c in significant), NO_CAUSE),
            "family": family,
            "entries": entries,
            "fits": fits,
            "gains": gains,
            "rollouts": rolled,
        }

    current, current_rollouts = base, base_rollouts
    rounds: list[dict[str, Any]] = []
    while len(rounds) < config.max_rounds:
        found = one_round(current, current_rollouts)
        rounds.append(found)
        cause = found["verdict"]
        if cause == NO_CAUSE:
            break
        current, current_rollouts = found["fits"][cause], found["rollouts"][cause]
        present = (*present, cause)
    first = rounds[0]
    verdict = first["verdict"]
    final_model = compose(model, present)
    fits = {NO_CAUSE: base, **first["fits"]}
    rollouts = {NO_CAUSE: base_rollouts, **first["rollouts"]}
    gains = first["gains"]
    base_rmse = base_rollouts.rmse_per_vehicle(num_vehicles)
    causes = first["entries"]
    every_fit = {"none": base}
    for number, found in enumerate(rounds, start=1):
        for fit in found["fits"].values():
            every_fit[f"round {number}: {fit.model.name}"] = fit

    report = {
        "verdict": verdict,
        "verdict_is_possible_processing_artefact": artefacts.get(verdict),
        "model": final_model.name,
        "rounds": [
            {
                "round": number,
                "model": compose(model, tuple(r["verdict"] for r in rounds[: number - 1])).name,
                "tested": found["family"],
                "verdict": found["verdict"],
                "causes": found["entries"],
            }
            for number, found in enumerate(rounds, start=1)
        ],
        "power_warning": power_warning(len(series.vehicle_ids)),
        "seed": seed,
        "base_model": model.name,
        "data": {
            "source": str(traj.source),
            "format": traj.format,
            "vehicles": len(series.vehicle_ids),
            "scored_steps_fit": int(series.windows.fit.sum()),
            "scored_steps_heldout": int(series.windows.heldout.sum()),
            "dt_s": series.dt,
            "split_rule": SPLIT_RULE,
            "history_s": series.history * series.dt,
        },
        "settings": {
            **config._asdict(),
            "causes": list(config.causes),
            "gain": "held-out log predictive density (leave-future-out), summed over vehicles",
            "se": "across vehicles: sqrt(N) * sd of the per-vehicle gains",
            "significance": "one-sided t-test (N-1 df) across vehicles of sign(g) log(1 + |g|) "
            f"of the per-vehicle gains g; Holm-Bonferroni at {config.alpha} over all "
            f"{len(config.causes)} causes considered (unfitted causes count as p = 1)",
            "screening": f"a cause is fitted when a screening check (calibrated across "
            f"vehicles) pointing to it has p < {config.screen_p} (Bonferroni within the cause)",
            "rounds": f"at most {config.max_rounds}; each extends the model by the round before's "
            "verdict and tests every screened cause that composes with it, Holm at "
            f"{config.alpha} over the causes that compose; a round runs only after a verdict "
            "(fixed-sequence gate: on null data the first round's false-positive rate)",
        },
        "base": {
            "elpd": float(base.log_z_held.sum()),
            "log_evidence_fit": float(base.log_z_fit.sum()),
            "rmse_position_m": float(np.nanmean(base_rmse)) if windows.row.size else None,
            "rollout_start": base_rollouts.start,
            "posterior": _posterior_summary(base, base.names),
        },
        "checks": [
            {
                "name": c.name,
                "title": c.title,
                "statistic": _finite_or_none(c.statistic),
                "p_value": c.p_value,
                "points_to": list(c.points_to),
                "summary": c.summary,
            }
            for c in checks
        ],
        "causes": causes,
        "timing": {
            "total_s": time.perf_counter() - started,
            "compile_s": {c: f.compile_time_s for c, f in every_fit.items()},
            "run_s": {c: f.run_time_s for c, f in every_fit.items()},
        },
        "sampler": {
            c: {
                "mean_stages_fit": float(f.stages_fit.mean()),
                "mean_stages_heldout": float(f.stages_held.mean()),
                "vehicles_bridged_from_base": int((~f.from_prior).sum()),
                "acceptance": float(f.acceptance.mean()),
            }
            for c, f in every_fit.items()
        },
    }
    return CriticismResult(report, checks, residuals, series, fits, gains, rollouts, current)
