"""Closed-loop evaluation scenarios: platoons and merges of real vehicles over held-out data.

**Platoon scenario** (:func:`platoon_scenarios`): an ordered chain ``head, f_1, ..., f_N`` of
vehicles in one lane over a window ``[t0, t0 + H]`` where, at every sample of the window, every
vehicle is present, ``f_k``'s leader (the ``leader_id`` link) is ``f_{k-1}`` (``f_0`` = head) and
no sample of the chain is flagged. The head replays the data; ``f_1 .. f_N`` are simulated closed
loop (``f_k`` follows the *simulated* ``f_{k-1}``). The window lies inside the held-out window of
every simulated vehicle (``t0 >= split_time`` of each, :mod:`bayesdrive.data.views`), so nothing
scored was fitted. ``N`` (``vehicles_per_scenario``) counts the simulated vehicles only.

Positions are re-anchored at t0: each follower's observed track is shifted by a constant so that
its bumper gap to its leader at t0 equals the measured ``gap``. Where positions and gaps agree
(NGSIM: positions define the gaps) the shift is 0; OpenACC positions are integrated Doppler speeds
that drift from the measured inter-vehicle spacing by metres over a recording (reader notes), so
without it a simulation would start from a gap off by up to tens of metres, even negative. Within a
window the drift is small; :attr:`ScenarioSet.summary` reports the shifts.

Chains come from the follower -> leader links of the whole data set, so deduplicated NGSIM
vehicles join chains from different files into longer platoons (connected components); lane
changes and cut-ins end a chain because the link must hold at every sample of the window.
Selection (:data:`SELECTION_RULE`, fixed and independent of any result): candidate windows are
visited in order of start time (ties: the chain's vehicle ids, front first); a window is accepted
unless one of its simulated vehicles is already simulated in an accepted scenario at an
overlapping time. Along one chain the windows are therefore non-overlapping, starting at the first
sample where all of its vehicles are in their held-out windows; the head may be reused.

**Merge scenario** (:func:`merge_scenarios`, data of the ``merge_episodes`` reader): the merging
car (the episode's ``*_ego`` vehicle) and the car ahead of it on the acceleration lane replay;
the main-lane car just behind the merging car (the "V2" slot: at each step, the main-lane car with
the largest position behind the merging car) is the cooperating driver and is simulated, following
whichever car leads it in the data (replayed). One scenario per such car and episode, from its
first step as V2 until it stops being V2, the episode ends or the horizon is reached, if that lasts
at least :data:`MIN_MERGE_WINDOW_S`. Positions stay on the reader's axis, the merge point (end of
the acceleration lane) at x = 0. Episodes are split, not vehicles (:data:`MERGE_SPLIT_RULE`).
"""

from __future__ import annotations

import re
from typing import Any, Literal, NamedTuple

import numpy as np

from bayesdrive.data.errors import DataError
from bayesdrive.data.readers.merge_episodes import FORMAT as MERGE_FORMAT
from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.views import (
    FIT_FRACTION,
    SPLIT_RULE,
    AheadArrays,
    FollowerArrays,
    MergeArrays,
    follower_arrays,
    history_steps,
    split_time,
)
from bayesdrive.drivers.base import Series

__all__ = [
    "MERGE_FIT_STAY_S",
    "MERGE_FORMAT",
    "MERGE_SELECTION_RULE",
    "MERGE_SPLIT_RULE",
    "MIN_MERGE_WINDOW_S",
    "SELECTION_RULE",
    "Scenario",
    "ScenarioSet",
    "fit_input",
    "fitting_episodes",
    "heldout_episodes",
    "merge_fit_arrays",
    "merge_follower_arrays",
    "merge_scenarios",
    "platoon_scenarios",
    "scenario_capacity",
    "with_history",
]

MIN_MERGE_WINDOW_S = 1.0
# A cooperating car's stay behind the merging car is fitted up to this long (longer ones are cut).
MERGE_FIT_STAY_S = 20.0
MERGE_SPLIT_RULE = (
    f"merge episodes in episode-number order: the first {FIT_FRACTION:.0%} (rounded down) are for "
    "fitting, the rest held out"
)
MERGE_SELECTION_RULE = (
    "every stay of a main-lane car as the car just behind the merging car (V2) in a held-out "
    f"episode, cut at the horizon, kept when it lasts at least {MIN_MERGE_WINDOW_S} s"
)
SELECTION_RULE = (
    "windows of H seconds inside every simulated vehicle's held-out window, visited by start time "
    "(ties: vehicle ids, front first); a window is kept unless a simulated vehicle is already "
    "simulated in a kept window at an overlapping time (the replayed head may repeat)"
)


class Scenario(NamedTuple):
    """One scene window to simulate; observed arrays in float64 on the data's position axis.

    vehicle_ids: the replayed leader of the first simulated vehicle (for a merge scene, the
        ids of the cars it follows during the window, joined by "|"), then the simulated vehicles
        front to back (N + 1 entries).
    t0: start time (s); the window has ``steps`` transitions of ``dt`` seconds, of which
        ``step_mask`` (T,) marks the real ones (a merge scene may end before the horizon).
    x, v: (N + 1, T + 1) observed positions (m) and speeds (m/s), the replayed leader in row 0
        (0 where ``head_present`` is 0 or past the end).
    gap: (N, T + 1) observed bumper gap of each simulated vehicle to its leader (the data's
        ``gap``; NaN where it has none).
    length: (N + 1,) vehicle lengths (m).
    anchor_shift: (N,) constant added to each simulated vehicle's observed positions so that its
        bumper gap at t0 is the measured gap (platoons; 0 for merge scenes).
    origin: the position subtracted before simulating in float32 (the head's start for a
        platoon, 0 = the merge point for a merge scene, whose model needs that axis).
    merge_x, merge_v, merge_present: (K, T + 1) replayed merge-lane vehicles; merge_length (K,).
    past: the simulated vehicles' observed series over the ``history_steps(dt)`` steps before t0
        (:class:`~bayesdrive.drivers.base.Series` of (N, K) arrays), what the ``filtered`` start
        reads (:func:`with_history`); None where not taken.
    """

    scenario_id: str
    vehicle_ids: tuple[str, ...]
    t0: float
    steps: int
    dt: float
    x: np.ndarray
    v: np.ndarray
    gap: np.ndarray
    length: np.ndarray
    anchor_shift: np.ndarray
    head_present: np.ndarray
    step_mask: np.ndarray
    origin: float
    merge_x: np.ndarray
    merge_v: np.ndarray
    merge_present: np.ndarray
    merge_length: np.ndarray
    past: Series | None = None

    @property
    def simulated_ids(self) -> tuple[str, ...]:
        return self.vehicle_ids[1:]


class ScenarioSet(NamedTuple):
    """The scenarios a data set allows for one size and horizon, with how they were chosen.

    kind: "platoon" or "merge". candidates: distinct chains of the requested size found in the
    leader links (platoons) or V2 stays in held-out episodes (merges).
    flagged_samples_skipped: flagged samples of candidate vehicles inside their held-out windows
        (windows touching them are not used).
    """

    kind: str
    scenarios: list[Scenario]
    vehicles_per_scenario: int
    horizon_s: float
    steps: int
    dt: float
    source: str
    candidates: int
    flagged_samples_skipped: int
    split_rule: str
    selection_rule: str

    @property
    def num_vehicles(self) -> int:
        return len(self.scenarios) * self.vehicles_per_scenario

    @property
    def simulated_ids(self) -> list[str]:
        """Distinct simulated vehicle ids, in order of first appearance."""
        return list(dict.fromkeys(v for s in self.scenarios for v in s.simulated_ids))

    def first(self, count: int | None) -> ScenarioSet:
        """The first ``count`` scenarios in the selection rule's order (None: all of them)."""
        return self if count is None else self._replace(scenarios=self.scenarios[:count])

    def within(self, vehicle_ids: set[str]) -> ScenarioSet:
        """The scenarios whose simulated vehicles are all among ``vehicle_ids`` (for example
        those with a fit: a vehicle without a usable fitting step has none)."""
        kept = [s for s in self.scenarios if set(s.simulated_ids) <= vehicle_ids]
        return self._replace(scenarios=kept)

    def anchor_shift_summary(self) -> dict[str, float] | None:
        """Median and largest |shift| (m) that re-anchored observed positions (None: no scenes)."""
        if not self.scenarios:
            return None
        shifts = np.abs(np.concatenate([s.anchor_shift for s in self.scenarios]))
        return {"median": float(np.median(shifts)), "max": float(shifts.max())}

    def summary(self) -> dict[str, Any]:
        """JSON-ready description of the set: counts and the rules that chose it."""
        return {
            "kind": self.kind,
            "source": self.source,
            "scenarios": len(self.scenarios),
            "vehicles_per_scenario": self.vehicles_per_scenario,
            "simulated_vehicle_windows": self.num_vehicles,
            "distinct_simulated_vehicles": len(self.simulated_ids),
            "horizon_s": self.horizon_s,
            "candidates": self.candidates,
            "flagged_samples_skipped": self.flagged_samples_skipped,
            "anchor_shift_m": self.anchor_shift_summary(),
            "selection_rule": self.selection_rule,
            "split_rule": self.split_rule,
        }


class _Track(NamedTuple):
    """One vehicle on the integer step grid ``first .. first + len - 1`` (absent samples masked)."""

    first: int
    present: np.ndarray
    leader: np.ndarray
    flagged: np.ndarray
    x: np.ndarray
    v: np.ndarray
    gap: np.ndarray
    length: np.ndarray
    heldout_from: int

    @property
    def last(self) -> int:
        return self.first + len(self.present) - 1


def _horizon_steps(traj: Trajectories, horizon_s: float) -> int:
    steps = round(horizon_s / traj.dt)
    if steps < 1 or not np.isclose(steps * traj.dt, horizon_s):
        raise DataError(
            f"{traj.source}: horizon {horizon_s} s is not a positive multiple of the sampling "
            f"interval {traj.dt} s"
        )
    return steps


def _tracks_on_grid(traj: Trajectories) -> dict[str, _Track]:
    flagged_steps: dict[str, set[int]] = {}
    for vid, t in zip(traj.flags["vehicle_id"], traj.flags["t"], strict=True):
        flagged_steps.setdefault(vid, set()).add(round(float(t) / traj.dt))
    tracks = {}
    for vid, rows in traj.tracks.groupby("vehicle_id", sort=False):
        steps = np.round(rows["t"].to_numpy() / traj.dt).astype(np.int64)
        first, span = int(steps[0]), int(steps[-1] - steps[0] + 1)
        at = steps - first

        def on_grid(values: np.ndarray, fill, dtype, at=at, span=span) -> np.ndarray:
            out = np.full(span, fill, dtype=dtype)
            out[at] = values
            return out

        present = on_grid(np.ones(len(at), bool), False, bool)
        flagged = np.zeros(span, bool)
        marks = [s - first for s in flagged_steps.get(vid, ()) if 0 <= s - first < span]
        flagged[marks] = True
        tracks[vid] = _Track(
            first=first,
            present=present,
            leader=on_grid(rows["leader_id"].to_numpy(dtype=object), None, object),
            flagged=flagged,
            x=on_grid(rows["x"].to_numpy(np.float64), np.nan, np.float64),
            v=on_grid(rows["v"].to_numpy(np.float64), np.nan, np.float64),
            gap=on_grid(rows["gap"].to_numpy(np.float64), np.nan, np.float64),
            length=on_grid(rows["length"].to_numpy(np.float64), np.nan, np.float64),
            heldout_from=round(split_time(rows["t"].to_numpy()) / traj.dt),
        )
    return tracks


def _chains(tracks: dict[str, _Track], size: int) -> list[tuple[str, ...]]:
    """All chains head, f_1 .. f_size linked follower -> leader somewhere in the data."""
    followers: dict[str, set[str]] = {}
    for vid, track in tracks.items():
        for lead in set(track.leader[track.present]) - {None}:
            followers.setdefault(lead, set()).add(vid)
    chains: list[tuple[str, ...]] = []

    def extend(chain: tuple[str, ...]) -> None:
        if len(chain) == size + 1:
            chains.append(chain)
            return
        for nxt in sorted(followers.get(chain[-1], ())):
            if nxt not in chain:
                extend((*chain, nxt))

    for head in sorted(tracks):
        extend((head,))
    return chains


def _valid_starts(
    chain: tuple[str, ...], tracks: dict[str, _Track], steps: int
) -> tuple[int, np.ndarray, int]:
    """(first grid step, valid-start mask, flagged samples hit) of windows along one chain."""
    members = [tracks[v] for v in chain]
    lo = max(max(t.first for t in members), max(t.heldout_from for t in members[1:]))
    hi = min(t.last for t in members)
    if hi - lo < steps:
        return lo, np.zeros(0, bool), 0
    ok = np.ones(hi - lo + 1, bool)
    flagged_hits = 0
    for k, track in enumerate(members):
        part = slice(lo - track.first, hi - track.first + 1)
        ok &= track.present[part] & ~track.flagged[part]
        flagged_hits += int(track.flagged[part].sum()) if k > 0 else 0
        if k > 0:
            ok &= track.leader[part] == chain[k - 1]
    # A start is valid when all steps + 1 samples of its window are usable.
    run = np.concatenate([[0], np.cumsum(ok)])
    window_ok = run[steps + 1 :] - run[: -steps - 1] == steps + 1
    return lo, window_ok, flagged_hits


def _scenario(chain, start: int, steps: int, tracks, dt: float) -> Scenario:
    members = [tracks[v] for v in chain]

    def window(track: _Track, values: np.ndarray) -> np.ndarray:
        return values[start - track.first : start - track.first + steps + 1]

    x = np.stack([window(t, t.x) for t in members])
    gap = np.stack([window(t, t.gap) for t in members[1:]])
    length = np.array([window(t, t.length)[0] for t in members])
    # Re-anchor each follower so its bumper gap at t0 is the measured one (module docstring).
    shift = np.zeros(len(chain))
    for k in range(1, len(chain)):
        shift[k] = x[k - 1, 0] - length[k - 1] - gap[k - 1, 0] - x[k, 0]
        x[k] += shift[k]
    no_merge_lane = np.zeros((0, steps + 1))
    return Scenario(
        scenario_id=f"{chain[0]}+{len(chain) - 1}@{start * dt:.1f}s",
        vehicle_ids=tuple(chain),
        t0=start * dt,
        steps=steps,
        dt=dt,
        x=x,
        v=np.stack([window(t, t.v) for t in members]),
        gap=gap,
        length=length,
        anchor_shift=shift[1:],
        head_present=np.ones(steps + 1),
        step_mask=np.ones(steps),
        origin=float(x[0, 0]),
        merge_x=no_merge_lane,
        merge_v=no_merge_lane,
        merge_present=no_merge_lane,
        merge_length=np.zeros(0),
    )


def platoon_scenarios(
    traj: Trajectories, *, vehicles_per_scenario: int, horizon_s: float
) -> ScenarioSet:
    """Platoon scenarios of ``vehicles_per_scenario`` simulated followers behind a replayed head,
    ``horizon_s`` seconds long, chosen by :data:`SELECTION_RULE` (module docstring).

    Returns a possibly empty set; :func:`scenario_capacity` tells which sizes the data allows.
    """
    return _platoons(traj, _tracks_on_grid(traj), vehicles_per_scenario, horizon_s)


def _platoons(
    traj: Trajectories, tracks: dict[str, _Track], vehicles_per_scenario: int, horizon_s: float
) -> ScenarioSet:
    if vehicles_per_scenario < 1:
        raise ValueError(f"vehicles_per_scenario must be >= 1, got {vehicles_per_scenario}")
    steps = _horizon_steps(traj, horizon_s)
    chains = _chains(tracks, vehicles_per_scenario)

    candidates = []
    flagged_skipped = 0
    for chain in chains:
        lo, window_ok, flagged_hits = _valid_starts(chain, tracks, steps)
        flagged_skipped += flagged_hits
        candidates.extend((lo + int(i), chain) for i in np.flatnonzero(window_ok))
    candidates.sort()

    # Steps each vehicle is already simulated at: (vehicle -> list of (start, end)).
    claimed: dict[str, list[tuple[int, int]]] = {}
    scenarios = []
    for start, chain in candidates:
        end = start + steps
        clash = any(
            start < other_end and other_start < end
            for vid in chain[1:]
            for other_start, other_end in claimed.get(vid, ())
        )
        if clash:
            continue
        for vid in chain[1:]:
            claimed.setdefault(vid, []).append((start, end))
        scenarios.append(_scenario(chain, start, steps, tracks, traj.dt))
    return ScenarioSet(
        kind="platoon",
        scenarios=scenarios,
        vehicles_per_scenario=vehicles_per_scenario,
        horizon_s=float(horizon_s),
        steps=steps,
        dt=float(traj.dt),
        source=traj.source,
        candidates=len(chains),
        flagged_samples_skipped=flagged_skipped,
        split_rule=SPLIT_RULE,
        selection_rule=SELECTION_RULE,
    )


def with_history(scenarios: ScenarioSet, traj: Trajectories) -> tuple[ScenarioSet, int]:
    """The scenarios whose simulated vehicles all have ``history_steps(dt)`` usable steps right
    before t0 in ``traj``, each with those steps as its ``past`` (what the ``filtered`` start
    reads), and how many scenarios were left out for lacking them."""
    ids = sorted({vid for scenario in scenarios.scenarios for vid in scenario.simulated_ids})
    series = follower_arrays(traj, window="all", vehicle_ids=ids) if ids else None
    row_of = {} if series is None else {vid: i for i, vid in enumerate(series.vehicle_ids)}
    past_steps = history_steps(scenarios.dt)

    def history(vid: str, t0: float) -> np.ndarray | None:
        """The vehicle's steps before t0, or None without a usable history there."""
        row = row_of.get(vid)
        if row is None:
            return None
        at = np.flatnonzero(np.abs(series.t[row] - t0) < scenarios.dt / 2)
        if len(at) != 1 or at[0] < past_steps:
            return None
        steps = np.arange(at[0] - past_steps, at[0])
        return steps if series.mask[row, steps].all() else None

    def cut(values: np.ndarray, rows: list[int], steps: list[np.ndarray]) -> np.ndarray:
        return np.stack([values[row, step] for row, step in zip(rows, steps, strict=True)])

    kept = []
    for scenario in scenarios.scenarios:
        steps = [history(vid, scenario.t0) for vid in scenario.simulated_ids]
        if any(step is None for step in steps):
            continue
        rows = [row_of[vid] for vid in scenario.simulated_ids]
        fields = {
            name: cut(getattr(series, name), rows, steps)
            for name in ("v", "next_v", "dx", "gap", "lead_v", "has_leader", "mask")
        }
        ahead = AheadArrays(*(cut(values, rows, steps) for values in series.ahead))
        past = Series(**fields, dt=np.full_like(fields["v"], scenarios.dt), ahead=ahead)
        kept.append(scenario._replace(past=past))
    dropped = len(scenarios.scenarios) - len(kept)
    return scenarios._replace(scenarios=kept), dropped


def scenario_capacity(traj: Trajectories, *, horizon_s: float, max_size: int = 30) -> list[dict]:
    """How many platoon scenarios and simulated vehicle-windows each size allows (sizes 1 ..
    ``max_size``, stopping at the first size with none)."""
    tracks = _tracks_on_grid(traj)
    rows = []
    for size in range(1, max_size + 1):
        found = _platoons(traj, tracks, size, horizon_s)
        if not found.scenarios:
            break
        rows.append(
            {
                "vehicles_per_scenario": size,
                "scenarios": len(found.scenarios),
                "vehicles": found.num_vehicles,
            }
        )
    return rows


def _natural_key(text: str) -> list:
    """Sort "ep2" before "ep10"."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", text)]


def heldout_episodes(traj: Trajectories) -> list[str]:
    """Scene ids of the held-out merge episodes (:data:`MERGE_SPLIT_RULE`)."""
    ordered = sorted(traj.scene_ids, key=_natural_key)
    return ordered[int(np.floor(FIT_FRACTION * len(ordered))) :]


def fitting_episodes(traj: Trajectories) -> list[str]:
    """Scene ids of the merge episodes for fitting, the complement of :func:`heldout_episodes`."""
    held_out = set(heldout_episodes(traj))
    return [e for e in sorted(traj.scene_ids, key=_natural_key) if e not in held_out]


def _on_steps(track: _Track, values: np.ndarray, steps: np.ndarray, fill) -> np.ndarray:
    """``values`` of a track at absolute grid steps, ``fill`` outside its span."""
    at = steps - track.first
    inside = (at >= 0) & (at < len(track.present))
    out = np.full(len(steps), fill, dtype=values.dtype)
    out[inside] = values[at[inside]]
    return out


def _cars_at(tracks: dict[str, _Track], ids: np.ndarray, steps: np.ndarray, field: str):
    """Per step, ``field`` of the car named in ``ids`` (None: no car), and whether it is there."""
    values = np.zeros(len(steps))
    present = np.zeros(len(steps), bool)
    for vid in set(ids) - {None}:
        track = tracks[vid]
        here = (ids == vid) & _on_steps(track, track.present, steps, False)
        values[here] = _on_steps(track, getattr(track, field), steps, np.nan)[here]
        present |= here
    return values, present


def _v2_per_step(ego: _Track, main_lane: list[str], tracks: dict[str, _Track]) -> np.ndarray:
    """At each of the ego's steps, the main-lane car just behind it (None where there is none)."""
    steps = np.arange(ego.first, ego.last + 1)
    best = np.full(len(steps), -np.inf)
    chosen = np.full(len(steps), None, dtype=object)
    for vid in main_lane:
        track = tracks[vid]
        x = _on_steps(track, track.x, steps, np.nan)
        here = _on_steps(track, track.present, steps, False) & ego.present
        closer = here & (x < ego.x) & (x > best)
        best[closer] = x[closer]
        chosen[closer] = vid
    return chosen


def _runs(labels: np.ndarray) -> list[tuple[int, int, str]]:
    """Maximal runs (first index, last index, label) of equal non-None labels."""
    runs, start = [], 0
    for i in range(1, len(labels) + 1):
        if i == len(labels) or labels[i] != labels[start]:
            if labels[start] is not None:
                runs.append((start, i - 1, labels[start]))
            start = i
    return runs


def merge_scenarios(
    traj: Trajectories,
    *,
    horizon_s: float,
    episodes: Literal["heldout", "fit", "all"] = "heldout",
) -> ScenarioSet:
    """Merge scenarios of the held-out episodes (module docstring), or of the fitting (or all)
    episodes for fitting a merging model, each at most ``horizon_s`` long; steps past an earlier
    end are padded (``step_mask`` = 0)."""
    steps = _horizon_steps(traj, horizon_s)
    min_steps = round(MIN_MERGE_WINDOW_S / traj.dt)
    tracks = _tracks_on_grid(traj)
    lane_of = traj.tracks.groupby("vehicle_id", sort=False)["lane_id"].first()
    scenarios, candidates, flagged_skipped = [], 0, 0
    chosen = {
        "heldout": heldout_episodes,
        "fit": fitting_episodes,
        "all": lambda t: sorted(t.scene_ids, key=_natural_key),
    }[episodes](traj)
    for episode in chosen:
        members = traj.scene_vehicles(episode)
        egos = [v for v in members if v.endswith("_ego")]
        if len(egos) != 1:
            raise DataError(
                f"{traj.source}: merge episode {episode!r} has {len(egos)} merging cars (ids "
                "ending in _ego); expected exactly 1"
            )
        ego_id = egos[0]
        ego = tracks[ego_id]
        main_lane = [v for v in members if lane_of[v] != lane_of[ego_id]]
        for first, last, v2 in _runs(_v2_per_step(ego, main_lane, tracks)):
            candidates += 1
            real = min(last - first, steps)
            if real < min_steps:
                continue
            window = np.arange(ego.first + first, ego.first + first + steps + 1)
            scenario = _merge_scenario(episode, ego_id, v2, window, real, tracks, traj)
            if scenario is None:
                flagged_skipped += 1
                continue
            scenarios.append(scenario)
    return ScenarioSet(
        kind="merge",
        scenarios=scenarios,
        vehicles_per_scenario=1,
        horizon_s=float(horizon_s),
        steps=steps,
        dt=float(traj.dt),
        source=traj.source,
        candidates=candidates,
        flagged_samples_skipped=flagged_skipped,
        split_rule=MERGE_SPLIT_RULE,
        selection_rule=MERGE_SELECTION_RULE,
    )


def _merge_scenario(
    episode: str,
    ego_id: str,
    v2: str,
    window: np.ndarray,
    real: int,
    tracks: dict[str, _Track],
    traj: Trajectories,
) -> Scenario | None:
    """One V2 stay as a scenario; None when a sample it needs is flagged."""
    in_scene = np.arange(len(window)) <= real
    car, ego = tracks[v2], tracks[ego_id]
    leaders = np.where(in_scene, _on_steps(car, car.leader, window, None), None)
    ego_leaders = np.where(in_scene, _on_steps(ego, ego.leader, window, None), None)
    needed = [(car, in_scene)] + [
        (tracks[vid], in_scene & (leaders == vid)) for vid in set(leaders) - {None}
    ]
    if any((_on_steps(t, t.flagged, window, False) & mask).any() for t, mask in needed):
        return None
    head_x, head_present = _cars_at(tracks, leaders, window, "x")
    head_v, _ = _cars_at(tracks, leaders, window, "v")
    lead_x, lead_present = _cars_at(tracks, ego_leaders, window, "x")
    lead_v, _ = _cars_at(tracks, ego_leaders, window, "v")
    ego_x = np.where(in_scene, _on_steps(ego, ego.x, window, 0.0), 0.0)
    ego_v = np.where(in_scene, _on_steps(ego, ego.v, window, 0.0), 0.0)
    leader_ids = sorted(set(leaders) - {None}, key=_natural_key)
    lengths = {float(np.nanmax(tracks[vid].length)) for vid in leader_ids}
    if len(lengths) > 1:
        raise DataError(
            f"{traj.source}: in merge episode {episode!r} the cars leading {v2} have different "
            f"lengths {sorted(lengths)}; the simulator takes one leader length per scene"
        )
    ego_lead_ids = set(ego_leaders) - {None}

    def length(ids) -> float:
        return float(np.nanmax([np.nanmax(tracks[vid].length) for vid in ids])) if ids else 0.0

    return Scenario(
        scenario_id=f"{episode}:{v2}@{window[0] * traj.dt:.1f}s",
        vehicle_ids=("|".join(leader_ids) or "none", v2),
        t0=float(window[0] * traj.dt),
        steps=len(window) - 1,
        dt=float(traj.dt),
        x=np.stack([head_x, np.where(in_scene, _on_steps(car, car.x, window, 0.0), 0.0)]),
        v=np.stack([head_v, np.where(in_scene, _on_steps(car, car.v, window, 0.0), 0.0)]),
        gap=np.where(in_scene, _on_steps(car, car.gap, window, np.nan), np.nan)[None],
        length=np.array([length(leader_ids), float(np.nanmax(car.length))]),
        anchor_shift=np.zeros(1),
        head_present=head_present.astype(np.float64),
        step_mask=(np.arange(len(window) - 1) < real).astype(np.float64),
        origin=0.0,
        merge_x=np.stack([ego_x, lead_x]),
        merge_v=np.stack([ego_v, lead_v]),
        merge_present=np.stack([in_scene, lead_present]).astype(np.float64),
        merge_length=np.array([length([ego_id]), length(ego_lead_ids)]),
    )


def merge_follower_arrays(scenarios: ScenarioSet) -> FollowerArrays:
    """The cooperating (V2) car's observed steps of merge scenarios as fitting arrays, with the
    merge scene beside each step; one row per scenario (a V2 stay), named by its scenario id.

    A step is usable where the scene is real and the car has a leader with a measured gap (as in
    :func:`~bayesdrive.data.views.follower_arrays`, the free-road term alone leaves d_min, tau and
    b_pref unidentified); stays without any usable step are left out. Positions are on the merge-point axis, so distances to the merge point
    are minus the positions; increments are differenced in float64.
    """
    if scenarios.kind != "merge":
        raise ValueError(f"merge_follower_arrays needs merge scenarios, got {scenarios.kind!r}")
    if not scenarios.scenarios:
        raise DataError(f"{scenarios.source}: no merge scenario to fit")

    # A stay without one usable step (no measured leader) would only add prior draws to a pool.
    fitted = [s for s in scenarios.scenarios if (s.step_mask * s.head_present[:-1]).any()]

    def rows(field) -> np.ndarray:
        return np.stack([field(s) for s in fitted])

    gap = rows(lambda s: s.gap[0, :-1])
    has_leader = rows(lambda s: s.head_present[:-1]) * np.isfinite(gap)
    lengths = rows(lambda s: s.merge_length)[:, None, :]
    return FollowerArrays(
        vehicle_ids=tuple(s.scenario_id for s in fitted),
        v=rows(lambda s: s.v[1, :-1]),
        next_v=rows(lambda s: s.v[1, 1:]),
        dx=rows(lambda s: np.diff(s.x[1])),
        gap=np.where(has_leader > 0, gap, 10.0),
        lead_v=rows(lambda s: s.v[0, :-1]),
        has_leader=has_leader,
        mask=rows(lambda s: s.step_mask) * has_leader,
        t=rows(lambda s: s.t0 + s.dt * np.arange(s.steps)),
        dt=scenarios.dt,
        merge=MergeArrays(
            ego_to_merge=rows(lambda s: -s.x[1, :-1]),
            merge_to_merge=rows(lambda s: -s.merge_x[:, :-1].T),
            merge_v=rows(lambda s: s.merge_v[:, :-1].T),
            merge_length=np.repeat(lengths, scenarios.steps, axis=1),
            merge_present=rows(lambda s: s.merge_present[:, :-1].T),
        ),
    )


def fit_input(traj: Trajectories, window: str) -> Trajectories | FollowerArrays:
    """What ``fit`` is given for ``traj``: merge episodes as :func:`merge_fit_arrays`, other
    trajectories as they are."""
    return merge_fit_arrays(traj, window) if traj.format == MERGE_FORMAT else traj


def merge_fit_arrays(traj: Trajectories, window: str) -> FollowerArrays:
    """What a merging model is fitted on: every stay (up to :data:`MERGE_FIT_STAY_S`) of a
    cooperating car behind the merging car, with the merge scene beside each step; the fitting
    episodes for ``window="fit"`` (the split is by episode), every episode otherwise."""
    scenarios = merge_scenarios(
        traj, horizon_s=MERGE_FIT_STAY_S, episodes="fit" if window == "fit" else "all"
    )
    return merge_follower_arrays(scenarios)
