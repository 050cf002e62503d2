"""SUMO round trip: the exported drivers, run by SUMO behind the data's recorded leaders, against
the data and against bayesdrive's own rollouts of the same drivers (``bayesdrive validate sumo``).

**Windows** (:func:`leader_windows`): for every fitted vehicle of the result that the data hold,
consecutive non-overlapping stretches of ``horizon_s`` seconds inside one window of the split rule
(by default the held-out window, which the fit never saw), every step usable and one leader
throughout. Windows are fixed by rule, never by results. A window whose follower starts faster
than its driver's v_des is left out, logged and counted: SUMO refuses a car that starts above
its desired speed (``bayesdrive.simulation.sumo``), where bayesdrive's IDM brakes towards it.

**Rollouts**, each from the follower's recorded gap and speed at the window's start, with the
leader replaying its recorded speeds (positions by the trapezoid rule, as SUMO's ballistic update
moves it):

- ``sumo``: the exported vehicle type of the vehicle (:func:`~bayesdrive.simulation.sumo.per_vehicle_drivers`,
  posterior medians, written by :func:`~bayesdrive.simulation.sumo.vtype_distribution`) driven by
  SUMO's own IDM (an IDM result) or Krauss (a Gipps result, whose replayed leader announces the
  driver's b_lead as its apparentDecel) through libsumo;
- ``bayesdrive``: the same drivers (the same parameter values, execution noise 0 as SUMO carries
  none) through bayesdrive's rollout (:func:`bayesdrive.simulation.rollout.rollout`);
- ``bayesdrive_predictive``: bayesdrive's rollouts of the vehicle's posterior draws with their
  execution noise, what the export leaves out;
- ``sumo_control``: SUMO with one parameter of the drivers halved (:data:`CONTROL`: the IDM's
  ``tau``, Gipps' ``d_min``), a wrong export that must fail.

**Distances**: per quantity (bumper gap, speed, acceleration over the steps after each window's
start, pooled over windows), the 1-Wasserstein distance between two sources, with a 95% bootstrap
interval that resamples whole windows (steps within a window are dependent), the same windows for
both sources.

**Pass**: the upper end of every interval between ``sumo`` and ``bayesdrive`` is within
:data:`TOLERANCE`, and ``sumo_control`` misses it. For the IDM both sources integrate the same
difference equation, so what remains is bayesdrive's float32 arithmetic and SUMO's braking cap
(``emergencyDecel``), which binds only near a collision; the tolerance is a small fraction of
the data's own spread in each quantity. For Gipps the distances measure how far SUMO's Krauss
is from the fitted Gipps rule, which the same tolerance judges.
"""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np
import pandas as pd
import xarray as xr
from jax import Array
from scipy.stats import wasserstein_distance

from bayesdrive.data.readers._common import DEFAULT_LENGTH_M
from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.views import FollowerArrays, Window, follower_arrays
from bayesdrive.drivers.base import DriverModel
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.core.output import metadata
from bayesdrive.simulation.posterior import fixed_params, particles_by_vehicle
from bayesdrive.simulation.rollout import (
    broadcast_params,
    draw_particles,
    platoon_scene,
    rollout,
)
from bayesdrive.simulation.sumo import (
    Driver,
    follow_in_sumo,
    per_vehicle_drivers,
    straight_road,
    sumo_home,
    vtype_distribution,
    write_vtype_distribution,
)

__all__ = [
    "CONTROL",
    "QUANTITIES",
    "TOLERANCE",
    "LeaderWindows",
    "SumoValidation",
    "leader_braking",
    "leader_windows",
    "validate_sumo",
    "validated_model",
]

# Quantity -> unit; compared over the steps after each window's start.
QUANTITIES = {"gap": "m", "speed": "m/s", "acceleration": "m/s^2"}
# Largest 1-Wasserstein distance (upper 95% bound) between SUMO's and bayesdrive's rollouts of
# the same drivers that still counts as the same (module docstring).
TOLERANCE = {"gap": 0.05, "speed": 0.02, "acceleration": 0.02}
# The wrong export that must fail, per base model: one parameter halved.
CONTROL = {"idm": {"tau": 0.5}, "gipps": {"d_min": 0.5}}
CONFIDENCE = 0.95
log = logging.getLogger(__name__)

# Road beyond the farthest the leader drives in a window (m).
ROAD_MARGIN_M = 500.0


class LeaderWindows(NamedTuple):
    """Windows behind one recorded leader each: (window,) vehicle ids and start times (s);
    (window, T + 1) the leader's speed and the follower's recorded speed and bumper gap; dt (s)."""

    vehicle: tuple[str, ...]
    t0: np.ndarray
    lead_v: np.ndarray
    v: np.ndarray
    gap: np.ndarray
    dt: float


class SumoValidation(NamedTuple):
    """What :func:`validate_sumo` found.

    windows: the windows compared. left_out: "vehicle at t=..." of the windows left out, whose
    follower starts faster than its v_des (module docstring). paths: source -> (v, gap), each
    (window, rollout, T + 1). distances: one row per comparison and quantity (W1, its interval, the tolerance where it
    applies, and whether it is met). matched: SUMO's rollouts are within the tolerance of
    bayesdrive's; control: the control's parameter factors; control_failed: its rollouts are
    not within the tolerance.
    """

    windows: LeaderWindows
    left_out: list[str]
    paths: dict[str, tuple[np.ndarray, np.ndarray]]
    distances: pd.DataFrame
    matched: bool
    control: dict[str, float]
    control_failed: bool

    @property
    def passed(self) -> bool:
        """SUMO matches bayesdrive, and the check has the power to say when it does not."""
        return self.matched and self.control_failed

    @property
    def samples(self) -> dict[str, dict[str, np.ndarray]]:
        """Source -> quantity -> (window, rollouts * T) values compared (module docstring)."""
        return _compared_values(self.paths, self.windows.dt)


def leader_windows(
    traj: Trajectories,
    vehicle_ids: list[str],
    *,
    horizon_s: float,
    window: Window = "heldout",
) -> LeaderWindows:
    """Consecutive non-overlapping windows of ``horizon_s`` behind one recorded leader each
    (module docstring), for the vehicles ``vehicle_ids`` in that order."""
    arrays = follower_arrays(traj, window=window, vehicle_ids=vehicle_ids)
    horizon = round(horizon_s / arrays.dt)
    if horizon < 1:
        raise ValueError(f"the horizon {horizon_s} s is shorter than one step ({arrays.dt} s)")
    rows, starts = _window_starts(arrays, horizon)
    if not rows:
        raise ValueError(
            f"{traj.source}: no {horizon_s:g} s stretch behind one leader in the {window!r} window "
            f"of vehicle(s) {', '.join(vehicle_ids)}: shorten --horizon"
        )

    def cut(values: np.ndarray) -> np.ndarray:
        return np.stack([values[r, s : s + horizon + 1] for r, s in zip(rows, starts, strict=True)])

    return LeaderWindows(
        vehicle=tuple(arrays.vehicle_ids[r] for r in rows),
        t0=np.array([arrays.t[r, s] for r, s in zip(rows, starts, strict=True)]),
        lead_v=cut(arrays.lead_v),
        v=cut(arrays.v),
        gap=cut(arrays.gap),
        dt=arrays.dt,
    )


def _window_starts(arrays: FollowerArrays, horizon: int) -> tuple[list[int], list[int]]:
    """Rows and first steps of the windows: horizon + 1 usable steps with one leader (its age,
    in samples, grows by one each step)."""
    rows, starts = [], []
    for row in range(len(arrays.vehicle_ids)):
        usable = arrays.mask[row] > 0
        age = arrays.ahead.lead_age[row]
        start = 0
        while start + horizon + 1 <= usable.shape[0]:
            span = slice(start, start + horizon + 1)
            same_leader = np.all(np.diff(age[span]) == 1)
            if usable[span].all() and same_leader:
                rows.append(row)
                starts.append(start)
                start += horizon + 1
            else:
                start += 1
    return rows, starts


def _quantities(v: np.ndarray, gap: np.ndarray, dt: float) -> dict[str, np.ndarray]:
    """Per window, the compared values pooled over rollouts and the steps after the start:
    (window, rollouts * T) each; v and gap are (window, rollout, T + 1)."""
    num_windows = v.shape[0]
    values = {
        "gap": gap[..., 1:],
        "speed": v[..., 1:],
        "acceleration": np.diff(v, axis=-1) / dt,
    }
    return {name: value.reshape(num_windows, -1) for name, value in values.items()}


def _compared_values(
    paths: Mapping[str, tuple[np.ndarray, np.ndarray]], dt: float
) -> dict[str, dict[str, np.ndarray]]:
    return {name: _quantities(v, gap, dt) for name, (v, gap) in paths.items()}


def _bayesdrive_paths(
    key: Array,
    model: DriverModel,
    windows: LeaderWindows,
    param_sets: Callable[[Array, int], Any],
    num_rollouts: int,
) -> tuple[np.ndarray, np.ndarray]:
    """bayesdrive's rollouts (:func:`~bayesdrive.simulation.rollout.rollout`) of every window,
    ``param_sets(key, window)`` giving the model's parameters (leaves (num_rollouts, 1))."""
    v_out, gap_out = [], []
    for index, keys in enumerate(jax.random.split(key, (len(windows.vehicle), 2))):
        scene = platoon_scene(
            windows.lead_v[index],
            np.array([-(windows.gap[index, 0] + DEFAULT_LENGTH_M)]),
            windows.v[index, :1],
            length=DEFAULT_LENGTH_M,
            dt=windows.dt,
        )
        params = param_sets(keys[0], index)
        simulated = rollout(keys[1], model, params, scene, num_rollouts=num_rollouts)
        v_out.append(np.asarray(simulated.v[:, 0], np.float64))
        gap_out.append(np.asarray(simulated.gap[:, 0], np.float64))
    return np.stack(v_out), np.stack(gap_out)


def _sumo_paths(
    windows: LeaderWindows, drivers: Mapping[str, Driver], stepping: float, folder: Path
) -> tuple[np.ndarray, np.ndarray]:
    """SUMO's rollouts of every window, each vehicle's exported type behind its leader."""
    home = sumo_home()
    by_id = list(drivers.values())
    xml = vtype_distribution(by_id, distribution_id="validate", stepping=stepping, header="")
    vtypes = folder / "vtypes.xml"
    write_vtype_distribution(vtypes, xml)
    furthest = float(np.max(np.sum(windows.lead_v, axis=1) * windows.dt + windows.gap[:, 0]))
    net = straight_road(folder, home, furthest + DEFAULT_LENGTH_M + ROAD_MARGIN_M)
    v_out, gap_out = [], []
    for index, vehicle in enumerate(windows.vehicle):
        followed = follow_in_sumo(
            home,
            net,
            vtypes,
            f"validate_{drivers[vehicle].id}",
            windows.lead_v[index],
            gap=float(windows.gap[index, 0]),
            v0=float(windows.v[index, 0]),
            dt=windows.dt,
            leader_length=DEFAULT_LENGTH_M,
            folder=folder,
            **leader_braking(drivers[vehicle]),
        )
        v_out.append(followed.v[None])
        gap_out.append(followed.gap[None])
    return np.stack(v_out), np.stack(gap_out)


def _distance_rows(
    key: Array,
    sources: Mapping[str, dict[str, np.ndarray]],
    pairs: list[tuple[str, str]],
    num_bootstrap: int,
) -> list[dict[str, Any]]:
    """W1 of every pair and quantity with its window-bootstrap interval (module docstring)."""
    num_windows = next(iter(sources.values()))["gap"].shape[0]
    resamples = np.asarray(
        jax.random.randint(key, (num_bootstrap, num_windows), 0, num_windows), int
    )
    tail = (1.0 - CONFIDENCE) / 2.0
    rows = []
    for first, second in pairs:
        for name, unit in QUANTITIES.items():
            a, b = sources[first][name], sources[second][name]
            boot = [wasserstein_distance(a[r].ravel(), b[r].ravel()) for r in resamples]
            low, high = np.quantile(boot, [tail, 1.0 - tail])
            rows.append(
                {
                    "compared": f"{first} vs {second}",
                    "quantity": name,
                    "unit": unit,
                    "w1": float(wasserstein_distance(a.ravel(), b.ravel())),
                    "w1_low": float(low),
                    "w1_high": float(high),
                }
            )
    return rows


def leader_braking(driver: Driver) -> dict[str, float]:
    """What the replayed leader announces for SUMO's Krauss to plan with: Gipps' b_lead."""
    if "b_lead" in driver.params:
        return {"leader_apparent_decel": driver.params["b_lead"]}
    return {}


def _with_factors(drivers: list[Driver], factors: Mapping[str, float]) -> list[Driver]:
    return [
        d._replace(params={k: v * factors.get(k, 1.0) for k, v in d.params.items()})
        for d in drivers
    ]


def validated_model(tree: xr.DataTree) -> DriverModel:
    """The result's model if :func:`validate_sumo` runs it (a base model SUMO carries), else a
    one-line error naming it."""
    model = get_model(metadata(tree)["model"])
    if model.name not in CONTROL:
        raise ValueError(
            f"validate sumo runs {' and '.join(CONTROL)} results; the result is of "
            f"{model.name!r} (`bayesdrive export sumo` says what SUMO cannot carry)"
        )
    return model


def validate_sumo(
    key: Array,
    tree: xr.DataTree,
    traj: Trajectories,
    *,
    horizon_s: float = 5.0,
    window: Window = "heldout",
    num_vehicles: int | None = None,
    num_rollouts: int = 10,
    num_bootstrap: int = 200,
    stepping: float,
) -> SumoValidation:
    """Run the result's exported drivers (IDM or Gipps) in SUMO behind the data's recorded leaders and
    compare (module docstring). ``num_vehicles`` keeps the first fitted vehicles the data hold;
    ``num_rollouts`` is the number of posterior-predictive rollouts per window; ``stepping`` the
    SUMO IDM's sub-step (s, the fitted data's step length). The key splits into one key for the
    predictive rollouts, one for the deterministic rollouts and one for the bootstrap."""
    meta = metadata(tree)
    model = validated_model(tree)
    base = model.name
    drivers = {d.id.removeprefix("vehicle_"): d for d in per_vehicle_drivers(tree)}
    held = [v for v in drivers if v in set(traj.vehicle_ids)]
    if not held:
        raise ValueError(f"{traj.source} holds none of the result's fitted vehicles")
    held = held[:num_vehicles] if num_vehicles is not None else held
    windows = leader_windows(traj, held, horizon_s=horizon_s, window=window)
    v_des = np.array([drivers[v].params["v_des"] for v in windows.vehicle])
    too_fast = windows.v[:, 0] > v_des
    starts = zip(windows.vehicle, windows.t0, too_fast, strict=True)
    left_out = [f"{v} at t={t:g} s" for v, t, fast in starts if fast]
    if too_fast.all():
        raise ValueError(
            "every window's follower starts faster than its driver's v_des, which SUMO refuses"
        )
    if too_fast.any():
        log.warning(
            "%d of %d window(s) left out: the follower starts faster than its v_des, which SUMO "
            "refuses: %s",
            len(left_out),
            len(too_fast),
            ", ".join(left_out),
        )
        windows = LeaderWindows(
            tuple(v for v, fast in zip(windows.vehicle, too_fast, strict=True) if not fast),
            *(values[~too_fast] for values in windows[1:-1]),
            dt=windows.dt,
        )
    key_predictive, key_fixed, key_bootstrap = jax.random.split(key, 3)

    def exported(_key: Array, index: int) -> Any:
        params = {**drivers[windows.vehicle[index]].params, "sigma": 0.0}
        return broadcast_params(model.params_type(**params), 1, 1)

    names = tuple(meta["params"])
    draws = particles_by_vehicle(tree, names)
    fixed = fixed_params(model, meta)

    def posterior(draw_key: Array, index: int) -> Any:
        particles = draws[windows.vehicle[index]][None]
        return draw_particles(draw_key, model, names, particles, num_rollouts, fixed=fixed)

    paths = {
        "data": (windows.v[:, None], windows.gap[:, None]),
        "bayesdrive": _bayesdrive_paths(key_fixed, model, windows, exported, 1),
        "bayesdrive_predictive": _bayesdrive_paths(
            key_predictive, model, windows, posterior, num_rollouts
        ),
    }
    with tempfile.TemporaryDirectory(prefix="bayesdrive-sumo-") as folder:
        chosen = {v: drivers[v] for v in dict.fromkeys(windows.vehicle)}
        paths["sumo"] = _sumo_paths(windows, chosen, stepping, Path(folder))
        wrong = dict(zip(chosen, _with_factors(list(chosen.values()), CONTROL[base]), strict=True))
        paths["sumo_control"] = _sumo_paths(windows, wrong, stepping, Path(folder))
    sources = _compared_values(paths, windows.dt)
    pairs = [
        ("sumo", "bayesdrive"),
        ("sumo_control", "bayesdrive"),
        ("sumo", "data"),
        ("bayesdrive", "data"),
        ("bayesdrive_predictive", "data"),
    ]
    table = pd.DataFrame(_distance_rows(key_bootstrap, sources, pairs, num_bootstrap))
    checked = table["compared"].isin(["sumo vs bayesdrive", "sumo_control vs bayesdrive"])
    table["tolerance"] = np.where(checked, table["quantity"].map(TOLERANCE), np.nan)
    table["within_tolerance"] = np.where(
        checked, (table["w1_high"] <= table["tolerance"]).astype(object), None
    )
    matched = bool(table.loc[table["compared"] == "sumo vs bayesdrive", "within_tolerance"].all())
    control = table["compared"] == "sumo_control vs bayesdrive"
    control_failed = not bool(table.loc[control, "within_tolerance"].all())
    return SumoValidation(windows, left_out, paths, table, matched, CONTROL[base], control_failed)
