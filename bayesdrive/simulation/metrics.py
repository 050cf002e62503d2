"""Metrics of closed-loop rollouts against the observed held-out trajectories.

Per scenario (R rollouts of N simulated vehicles over T steps):

* **RMSE** of position and of speed at every horizon step t = 0..T, over vehicles and rollouts:
  :math:`\\sqrt{\\frac{1}{RN}\\sum_{r,n}(x^{sim}_{rnt} - x^{obs}_{nt})^2}` (a true root mean
  square). Beside it, labelled ``paper_mae_last_step``, the quantity the paper's code reported:
  the mean absolute error at the last step only.
* **Collisions**: events = onsets (a vehicle's bumper gap turning <= 0; a collision lasting
  several steps is one event); fraction = share of simulated vehicle-rollouts that collide at
  least once.
* **Hard braking**: vehicle-steps with realised acceleration <= -3 m/s^2, beside the same count
  in the data (observed speeds of the same vehicles and steps).
* **Undesirable events over time**: the share of simulated vehicle-rollouts that have collided,
  braked hard or left the road at least once by horizon step t (the paper's undesirable-event
  curve; cumulative, so it never decreases).
* **Proper scores** at the last step (the energy score over the whole path): the CRPS of each
  vehicle's position and speed over the rollouts and the energy score of its joint (gap, speed)
  path (steps 1..T, gap in 1 m, speed in 1 m/s; a step without a leader has no gap to forecast
  and adds 0), averaged over vehicles (:mod:`bayesdrive.simulation.calibration`, scoringrules).
  Lower is better; unlike the RMSE over rollouts they do not penalise a calibrated spread.
  Beside them the **predictive mean's** last-step position error (squared, averaged over
  vehicles; its root over scenarios is the predictive-mean RMSE), and the **calibration** of the
  last-step position: each vehicle's probability integral transform (the observed position's
  rank among the rollouts, ties at the mid-rank:
  :func:`~bayesdrive.simulation.calibration.pit_of_observation`), pooled over scenarios into the
  coverage of the central 50% and 90% intervals and a PIT histogram
  (:func:`~bayesdrive.simulation.calibration.pit_summary`).
* **Realism beside the data**: the jerk (the change of the realised acceleration; RMS and the
  distance of its distribution to the data's) and the share of vehicles whose minimum
  time-to-collision (gap over the closing speed read from the gap) falls below
  ``CRITICAL_TTC_S``, for the rollouts and for the observed vehicles alike.
* **Platoons** (:mod:`bayesdrive.simulation.platoon`): string stability, as the amplification of
  speed variation from each vehicle to the next, and the speed at which waves travel back
  (Newell's shift), for the rollouts and for the observed chain alike; merge scenes have none.
* **Off road**: vehicle-steps past the end of the vehicle's lane. No simulated vehicle of the
  current scene types drives on a lane that ends (in merge scenes the merging car replays), so
  this is 0 by construction there; it counts for scenes that simulate merging cars.

Across scenarios: mean and sample sd (ddof = 1; None with a single scenario) of the per-scenario
values, totals of the counts, and speed and gap distributions of all simulated vehicle-steps
against the observed ones: Wasserstein-1 distance and the two-sample Kolmogorov-Smirnov
statistic, and their kernel densities on a grid (:func:`speed_density`, for plots). :func:`kde`
evaluates a Gaussian KDE.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import numpy as np
from jax import Array
from scipy import stats

from bayesdrive.drivers.closed_loop import STATIONARY
from bayesdrive.simulation.baselines import Policy
from bayesdrive.simulation.calibration import crps, energy_score, pit_of_observation, pit_summary
from bayesdrive.simulation.platoon import platoon_measures, platoon_summary
from bayesdrive.simulation.rollout import HARD_BRAKING_MPS2, Rollout, rollout, scene_arrays
from bayesdrive.simulation.scenarios import Scenario, ScenarioSet

__all__ = [
    "CRITICAL_TTC_S",
    "DistributionSamples",
    "Observed",
    "ScenarioMetrics",
    "collision_onsets",
    "distribution_distance",
    "distribution_samples",
    "evaluate_policy",
    "evaluate_scenario",
    "kde",
    "minimum_ttc",
    "observed_data",
    "realised_jerk",
    "rmse_by_step",
    "scenario_keys",
    "scenario_metrics",
    "speed_density",
    "summarize",
]


class Observed(NamedTuple):
    """The data a rollout is scored against, on the rollout's axes.

    x, v, gap: (N, T + 1) observed position (from the scenario's origin), speed and bumper gap
    of the simulated vehicles (gap NaN where there is no leader). step_mask: (T,) 1 for real
    steps (0: past the end of the scene). dt: step length (s). head_x, head_v: (T + 1,) the
    replayed head of a platoon (each simulated vehicle follows the one before it); None for a
    scene that is not a chain (a merge), which has no platoon measures.
    """

    x: np.ndarray
    v: np.ndarray
    gap: np.ndarray
    step_mask: np.ndarray
    dt: float
    head_x: np.ndarray | None = None
    head_v: np.ndarray | None = None


class ScenarioMetrics(NamedTuple):
    """One scenario's metrics (module docstring); by-step arrays are NaN past the scene's end.

    collided: vehicle-rollouts that collide at least once, out of ``vehicles * rollouts``.
    undesirable_by_step: (T + 1,) share of vehicle-rollouts with an undesirable event by step t.
    pit_position_last: (N,) each vehicle's PIT of its observed last-step position.
    """

    scenario_id: str
    vehicles: int
    rollouts: int
    rmse_position_by_step: np.ndarray
    rmse_speed_by_step: np.ndarray
    mae_position_last: float
    mae_speed_last: float
    collisions: int
    collided: int
    hard_braking: int
    data_hard_braking: int
    off_road: int
    undesirable_by_step: np.ndarray
    crps_position_last: float
    crps_speed_last: float
    energy_score_path: float
    predictive_mean_sq_error_last: float
    pit_position_last: np.ndarray

    @property
    def last_step(self) -> int:
        return int(np.flatnonzero(np.isfinite(self.rmse_position_by_step))[-1])


class DistributionSamples(NamedTuple):
    """Speeds and gaps of every real simulated vehicle-step (t >= 1) and of the data there; the
    jerk of every real step with two real steps after it (:func:`realised_jerk`); each simulated
    vehicle-rollout's and each observed vehicle's minimum time-to-collision (:func:`minimum_ttc`);
    on a platoon, each consecutive pair's speed variances and Newell shift
    (:func:`~bayesdrive.simulation.platoon.platoon_measures`; (0, 2) arrays elsewhere)."""

    simulated_speed: np.ndarray
    observed_speed: np.ndarray
    simulated_gap: np.ndarray
    observed_gap: np.ndarray
    simulated_jerk: np.ndarray
    observed_jerk: np.ndarray
    simulated_min_ttc: np.ndarray
    observed_min_ttc: np.ndarray
    simulated_speed_variances: np.ndarray
    observed_speed_variances: np.ndarray
    simulated_newell_shifts: np.ndarray
    observed_newell_shifts: np.ndarray


def observed_data(scenario: Scenario) -> Observed:
    """The observed simulated vehicles of a scenario, positions from the scenario's origin."""
    chain = scenario.merge_x.shape[0] == 0  # a merge scene's followed car changes
    return Observed(
        x=scenario.x[1:] - scenario.origin,
        v=scenario.v[1:],
        gap=scenario.gap,
        step_mask=scenario.step_mask,
        dt=scenario.dt,
        head_x=scenario.x[0] - scenario.origin if chain else None,
        head_v=scenario.v[0] if chain else None,
    )


def rmse_by_step(simulated: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """Root mean square error over rollouts and vehicles at each step.

    simulated: (R, N, T + 1); observed: (N, T + 1). Returns (T + 1,).
    """
    error = np.asarray(simulated, np.float64) - np.asarray(observed, np.float64)[None]
    return np.sqrt(np.mean(error**2, axis=(0, 1)))


def collision_onsets(collision: np.ndarray) -> int:
    """Number of collision events in a (..., T) boolean array: the steps where one begins."""
    collision = np.asarray(collision, bool)
    before = np.concatenate([np.zeros_like(collision[..., :1]), collision[..., :-1]], axis=-1)
    return int(np.sum(collision & ~before))


def scenario_metrics(scenario_id: str, rollout: Rollout, observed: Observed) -> ScenarioMetrics:
    """All per-scenario metrics of ``rollout`` (numpy or JAX arrays) against ``observed``."""
    x, v = np.asarray(rollout.x, np.float64), np.asarray(rollout.v, np.float64)
    num_rollouts, num_vehicles, _ = x.shape
    real = np.asarray(observed.step_mask) > 0
    past_end = np.concatenate([[False], ~real])
    last = int(np.flatnonzero(~past_end)[-1])
    collision = np.asarray(rollout.collision, bool)
    event = collision | np.asarray(rollout.hard_braking, bool) | np.asarray(rollout.off_road, bool)
    had_event = np.concatenate(
        [np.zeros((num_rollouts, num_vehicles, 1), bool), np.logical_or.accumulate(event, axis=-1)],
        axis=-1,
    )
    # (vehicle, rollout, step) errors over the real steps 1..last; no leader: no gap error.
    steps = slice(1, last + 1)
    gap_error = np.nan_to_num(np.asarray(rollout.gap, np.float64) - observed.gap[None])
    gap_error = np.moveaxis(gap_error[:, :, steps], 0, 1)
    speed_error = np.moveaxis((v - observed.v[None])[:, :, steps], 0, 1)
    # The simulator's realised-acceleration rule, applied to the observed speeds.
    observed_acceleration = np.diff(observed.v, axis=1) / observed.dt
    position_error = (x[:, :, last] - observed.x[None, :, last]).T  # (vehicle, rollout)
    return ScenarioMetrics(
        scenario_id=scenario_id,
        vehicles=num_vehicles,
        rollouts=num_rollouts,
        rmse_position_by_step=np.where(past_end, np.nan, rmse_by_step(x, observed.x)),
        rmse_speed_by_step=np.where(past_end, np.nan, rmse_by_step(v, observed.v)),
        mae_position_last=float(np.mean(np.abs(x[:, :, last] - observed.x[None, :, last]))),
        mae_speed_last=float(np.mean(np.abs(v[:, :, last] - observed.v[None, :, last]))),
        collisions=collision_onsets(collision),
        collided=int(np.sum(collision.any(axis=-1))),
        hard_braking=int(np.sum(rollout.hard_braking)),
        data_hard_braking=int(np.sum((observed_acceleration <= HARD_BRAKING_MPS2) & real)),
        off_road=int(np.sum(rollout.off_road)),
        undesirable_by_step=np.where(past_end, np.nan, had_event.mean(axis=(0, 1))),
        crps_position_last=float(crps(position_error).mean()),
        crps_speed_last=float(crps((v[:, :, last] - observed.v[None, :, last]).T).mean()),
        energy_score_path=float(energy_score(gap_error, speed_error).mean()),
        # The predictive mean's error, not the rollouts' (which penalises a calibrated spread).
        predictive_mean_sq_error_last=float(
            np.mean((x[:, :, last].mean(axis=0) - observed.x[:, last]) ** 2)
        ),
        pit_position_last=pit_of_observation(position_error, 0.5),
    )


def realised_jerk(v: np.ndarray, dt: float) -> np.ndarray:
    """Jerk (m/s^3) of speed series along their last axis (T + 1 states -> T - 1 jerks): the change
    of the realised acceleration (v' - v) / dt, the same rule for simulation and data."""
    return np.diff(v, n=2, axis=-1) / dt**2


def minimum_ttc(gap: np.ndarray, dt: float) -> np.ndarray:
    """Each series' (last axis) smallest time-to-collision (s): gap over closing speed, the
    closing speed read from the gap itself, -(gap' - gap) / dt, where it is positive; inf for a
    series that never closes on a leader (NaN gaps: no leader)."""
    closing = -np.diff(gap, axis=-1) / dt
    now = gap[..., :-1]
    closes = np.isfinite(now) & np.isfinite(closing) & (closing > 0)
    ttc = np.where(closes, now / np.where(closes, closing, 1.0), np.inf)
    return ttc.min(axis=-1)


def distribution_samples(rollout: Rollout, observed: Observed) -> DistributionSamples:
    """Pool the real steps t >= 1; gaps only where the vehicle has a leader (the replayed head's
    presence is the same in simulation and data, so the observed gap's NaNs mark it); jerks and
    minimum times-to-collision over the real states 0..last."""
    real = np.concatenate([[False], np.asarray(observed.step_mask) > 0])
    real_steps = np.broadcast_to(real, observed.v.shape)
    with_leader = real_steps & np.isfinite(observed.gap)
    states = slice(0, int(np.flatnonzero(real)[-1]) + 1 if real.any() else 1)
    simulated_v = np.asarray(rollout.v, np.float64)
    simulated_gap = np.asarray(rollout.gap, np.float64)
    none = np.zeros((0, 2))
    simulated_platoon = observed_platoon = (none, none)
    if observed.head_x is not None:
        head = (observed.head_x[states], observed.head_v[states])
        simulated_platoon = platoon_measures(
            *head, np.asarray(rollout.x)[..., states], simulated_v[..., states], observed.dt
        )
        observed_platoon = platoon_measures(
            *head, observed.x[:, states], observed.v[:, states], observed.dt
        )
    return DistributionSamples(
        simulated_speed=simulated_v[:, real_steps].ravel(),
        observed_speed=observed.v[real_steps],
        simulated_gap=simulated_gap[:, with_leader].ravel(),
        observed_gap=observed.gap[with_leader],
        simulated_jerk=realised_jerk(simulated_v[..., states], observed.dt).ravel(),
        observed_jerk=realised_jerk(observed.v[:, states], observed.dt).ravel(),
        simulated_min_ttc=minimum_ttc(simulated_gap[..., states], observed.dt).ravel(),
        observed_min_ttc=minimum_ttc(observed.gap[:, states], observed.dt).ravel(),
        simulated_speed_variances=simulated_platoon[0],
        observed_speed_variances=observed_platoon[0],
        simulated_newell_shifts=simulated_platoon[1],
        observed_newell_shifts=observed_platoon[1],
    )


SIDES = ("simulated", "observed")
# A minimum time-to-collision below this is a critical conflict (a threshold common in traffic
# conflict studies).
CRITICAL_TTC_S = 1.5


def _realism(pooled: Callable[[str], np.ndarray]) -> dict[str, Any]:
    """Jerk and minimum time-to-collision of the simulation, each beside the data's, from the
    samples ``pooled`` over the scenarios (by :class:`DistributionSamples` field)."""
    jerk = {side: pooled(f"{side}_jerk") for side in SIDES}
    ttc = {side: pooled(f"{side}_min_ttc") for side in SIDES}
    return {
        "jerk_mps3": {
            **{f"{side}_rms": float(np.sqrt(np.mean(j**2))) for side, j in jerk.items()},
            **distribution_distance(jerk["simulated"], jerk["observed"]),
        },
        "min_ttc": {
            "critical_s": CRITICAL_TTC_S,
            **{
                f"{side}_share_critical": float(np.mean(t < CRITICAL_TTC_S))
                for side, t in ttc.items()
            },
        },
    }


def distribution_distance(simulated: np.ndarray, observed: np.ndarray) -> dict[str, float]:
    """Wasserstein-1 distance (in the samples' unit) and two-sample KS statistic."""
    if len(simulated) == 0 or len(observed) == 0:
        raise ValueError("cannot compare distributions: one of the samples is empty")
    return {
        "wasserstein": float(stats.wasserstein_distance(simulated, observed)),
        "ks": float(stats.ks_2samp(simulated, observed).statistic),
    }


def kde(samples: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Gaussian kernel density (Scott's bandwidth) of ``samples`` evaluated on ``grid``."""
    return stats.gaussian_kde(np.asarray(samples, np.float64))(np.asarray(grid, np.float64))


# A kernel density from this many evenly strided samples differs from the full one by far less
# than a line's width; pooled rollouts hold up to millions.
DENSITY_SAMPLES = 50_000
DENSITY_GRID = 120


def speed_density(simulated: np.ndarray, observed: np.ndarray) -> dict[str, list[float]]:
    """Kernel densities of simulated and observed speeds on a shared grid (for plots)."""
    top = 1.05 * max(float(np.max(simulated)), float(np.max(observed)))
    grid = np.linspace(0.0, top, DENSITY_GRID)

    def density(samples: np.ndarray) -> list[float]:
        if np.ptp(samples) == 0:  # one repeated value (e.g. constant velocity): a KDE is singular
            width = grid[1] - grid[0]
            return stats.norm.pdf(grid, samples[0], width).tolist()
        stride = max(1, len(samples) // DENSITY_SAMPLES)
        return kde(samples[::stride], grid).tolist()

    return {
        "grid_mps": grid.tolist(),
        "simulated": density(simulated),
        "observed": density(observed),
    }


def _mean_sd(values) -> dict[str, float | None]:
    values = np.asarray(values, np.float64)
    return {
        "mean": float(np.mean(values)),
        "sd": float(np.std(values, ddof=1)) if len(values) > 1 else None,
    }


def _by_step(per_scenario: list[np.ndarray]) -> dict[str, list[float | None]]:
    """Mean and sd across the scenarios that reach each step (NaN past a scene's end)."""
    table = np.stack(per_scenario)
    reached = np.isfinite(table)
    means, sds = [], []
    for column, ok in zip(table.T, reached.T, strict=True):
        summary = _mean_sd(column[ok]) if ok.any() else {"mean": None, "sd": None}
        means.append(summary["mean"])
        sds.append(summary["sd"])
    return {"mean": means, "sd": sds}


def summarize(metrics: list[ScenarioMetrics], samples: list[DistributionSamples]) -> dict[str, Any]:
    """Across-scenario summary (module docstring), JSON-ready; "final" = each scene's last step."""
    if not metrics:
        raise ValueError("no scenarios to summarize")
    rollouts = metrics[0].rollouts
    vehicle_rollouts = sum(m.vehicles * m.rollouts for m in metrics)

    def final(name: str) -> dict[str, Any]:
        by_step = [getattr(m, name) for m in metrics]
        return {
            **_mean_sd([b[m.last_step] for b, m in zip(by_step, metrics, strict=True)]),
            "by_step": _by_step(by_step),
        }

    def pooled(name: str) -> np.ndarray:
        return np.concatenate([getattr(s, name) for s in samples])

    collisions = sum(m.collisions for m in metrics)
    hard_braking = sum(m.hard_braking for m in metrics)
    return {
        "scenarios": len(metrics),
        "vehicles": sum(m.vehicles for m in metrics),
        "rollouts": rollouts,
        "rmse_position_m": final("rmse_position_by_step"),
        "rmse_speed_mps": final("rmse_speed_by_step"),
        "paper_mae_last_step": {
            "note": "mean absolute error at the last step only, as the paper's code computed it",
            "position_m": _mean_sd([m.mae_position_last for m in metrics]),
            "speed_mps": _mean_sd([m.mae_speed_last for m in metrics]),
        },
        "collisions": {
            "total": collisions,
            "per_rollout": collisions / rollouts,
            "fraction": sum(m.collided for m in metrics) / vehicle_rollouts,
        },
        "hard_braking": {
            "total": hard_braking,
            "per_rollout": hard_braking / rollouts,
            "data_total": sum(m.data_hard_braking for m in metrics),
        },
        "off_road": {"total": sum(m.off_road for m in metrics)},
        "crps_position_m": _mean_sd([m.crps_position_last for m in metrics]),
        "crps_speed_mps": _mean_sd([m.crps_speed_last for m in metrics]),
        "energy_score_path": _mean_sd([m.energy_score_path for m in metrics]),
        "predictive_mean_rmse_position_m": float(
            np.sqrt(np.mean([m.predictive_mean_sq_error_last for m in metrics]))
        ),
        "calibration_position": pit_summary(np.concatenate([m.pit_position_last for m in metrics])),
        "undesirable_events": final("undesirable_by_step"),
        "speed_distribution_mps": distribution_distance(
            pooled("simulated_speed"), pooled("observed_speed")
        ),
        "gap_distribution_m": distribution_distance(
            pooled("simulated_gap"), pooled("observed_gap")
        ),
        "speed_density": speed_density(pooled("simulated_speed"), pooled("observed_speed")),
        **_realism(pooled),
        **platoon_summary(
            {side: pooled(f"{side}_speed_variances") for side in SIDES},
            {side: pooled(f"{side}_newell_shifts") for side in SIDES},
        ),
        "by_scenario": [
            {
                "scenario": m.scenario_id,
                "rmse_position_m": float(m.rmse_position_by_step[m.last_step]),
                "rmse_speed_mps": float(m.rmse_speed_by_step[m.last_step]),
                "crps_position_m": m.crps_position_last,
                "predictive_mean_sq_error_m2": m.predictive_mean_sq_error_last,
                "collisions": m.collisions,
                "hard_braking": m.hard_braking,
            }
            for m in metrics
        ],
    }


def evaluate_scenario(
    key: Array, policy: Policy, scenario: Scenario, *, num_rollouts: int, start: str = STATIONARY
) -> tuple[ScenarioMetrics, DistributionSamples]:
    """Run ``policy`` on one scenario from ``start``: ``key`` splits into a parameter-draw key and
    a rollout key. Returns the scenario's metrics and its distribution samples."""
    key_params, key_rollout = jax.random.split(key)
    params = policy.params_for(key_params, scenario.simulated_ids, num_rollouts)
    simulated = rollout(
        key_rollout,
        policy.model,
        params,
        scene_arrays(scenario),
        num_rollouts=num_rollouts,
        start=start,
    )
    data = observed_data(scenario)
    return scenario_metrics(scenario.scenario_id, simulated, data), distribution_samples(
        simulated, data
    )


def scenario_keys(key: Array, scenarios: ScenarioSet) -> Array:
    """One key per scenario, in the set's order (what :func:`evaluate_policy` gives each)."""
    return jax.random.split(key, len(scenarios.scenarios))


def evaluate_policy(
    key: Array,
    policy: Policy,
    scenarios: ScenarioSet,
    *,
    num_rollouts: int,
    start: str = STATIONARY,
    on_scenario: Callable[[ScenarioMetrics], None] | None = None,
) -> dict[str, Any]:
    """Run ``policy`` on every scenario from ``start`` (:func:`evaluate_scenario` with its key
    from :func:`scenario_keys`) and summarize (:func:`summarize`). ``on_scenario`` is called
    after each scenario (progress display).
    """
    if not scenarios.scenarios:
        raise ValueError(f"{scenarios.source}: no scenarios to evaluate")
    metrics, samples = [], []
    for scenario, scenario_key in zip(
        scenarios.scenarios, scenario_keys(key, scenarios), strict=True
    ):
        scored, sampled = evaluate_scenario(
            scenario_key, policy, scenario, num_rollouts=num_rollouts, start=start
        )
        metrics.append(scored)
        samples.append(sampled)
        if on_scenario is not None:
            on_scenario(scored)
    return summarize(metrics, samples)
