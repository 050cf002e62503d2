"""The one trajectory representation every reader produces and every other layer consumes.

A :class:`Trajectories` holds measured vehicle trajectories in SI units, one row per vehicle and
time step, plus which vehicles form which scene and which samples were flagged as physically
impossible. Every reader (``bayesdrive.data.readers``) converts its format into this; nothing
downstream ever sees feet, front-to-front headways or per-file time axes.

Columns of ``Trajectories.tracks`` (the schema is :data:`TRACK_COLUMNS`):

============  ========  ===================================================================
column        unit      meaning
============  ========  ===================================================================
vehicle_id    --        string id, unique within the data set (deduplicated across files)
t             s         time on the vehicle's (and its scene's) common time axis
x             m         longitudinal position along the lane, increasing in driving direction
v             m/s       speed (>= 0)
a             m/s^2     measured acceleration; NaN where the source has none
lane_id       --        lane id where known, else <NA> (nullable integer)
leader_id     --        id of the vehicle ahead in the same lane, else None
gap           m         bumper-to-bumper gap to the leader (rear of leader - front of ego),
                        NaN where there is no leader
length        m         vehicle length (documented assumption where the source has none)
driver        --        "human", "acc" or "unknown"
============  ========  ===================================================================

``scenes`` is a membership table (``scene_id``, ``vehicle_id``): a scene is a set of vehicles
recorded together (one NGSIM chain file, one OpenACC platoon recording, one merge episode). After
deduplication a vehicle may belong to several scenes. ``flags`` lists samples that are well-formed
but physically impossible (``vehicle_id``, ``t``, ``kind``, ``message``); the pairs they touch are
left out of fitting by default (see :func:`bayesdrive.data.views.leader_follower_pairs`).

Positions of vehicles that share a scene live on one axis, so ``x_leader - x - length_leader``
equals ``gap`` wherever both are present; readers either take ``gap`` from the source (OpenACC's
``IVS``) or compute it that way.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

__all__ = ["DRIVERS", "FLAG_COLUMNS", "REPAIR_PREFIX", "TRACK_COLUMNS", "Trajectories"]

TRACK_COLUMNS: dict[str, str] = {
    "vehicle_id": "object",
    "t": "float64",
    "x": "float64",
    "v": "float64",
    "a": "float64",
    "lane_id": "Int64",
    "leader_id": "object",
    "gap": "float64",
    "length": "float64",
    "driver": "object",
}
FLAG_COLUMNS = ["vehicle_id", "t", "kind", "message"]
DRIVERS = ("human", "acc", "unknown")
# Notes that record a change to the data start with this; ``read(strict=True)`` refuses them.
REPAIR_PREFIX = "repair: "


@dataclasses.dataclass(frozen=True)
class Trajectories:
    """Validated trajectories of one data set (see the module docstring for the schema).

    Attributes:
        tracks: one row per (vehicle_id, t), sorted by vehicle then time.
        scenes: membership table with columns ``scene_id`` and ``vehicle_id``.
        dt: sampling interval in seconds, shared by every vehicle.
        format: name of the reader that produced it (``"ngsim_chains"``, ``"openacc"``, ...).
        source: where it was read from (path or data set name).
        flags: physically impossible samples (columns :data:`FLAG_COLUMNS`).
        notes: documented assumptions and repairs the reader made (e.g. assumed lengths);
            repairs (changes to the data) start with :data:`REPAIR_PREFIX`.
        inputs: sha256 (hex) of every file read, by path, so a result names the exact bytes.
    """

    tracks: pd.DataFrame
    scenes: pd.DataFrame
    dt: float
    format: str
    source: str
    flags: pd.DataFrame = dataclasses.field(
        default_factory=lambda: pd.DataFrame(columns=FLAG_COLUMNS)
    )
    notes: tuple[str, ...] = ()
    inputs: Mapping[str, str] = dataclasses.field(default_factory=dict)

    @property
    def repairs(self) -> list[str]:
        """The changes made to the input data (the notes starting with :data:`REPAIR_PREFIX`)."""
        return [n[len(REPAIR_PREFIX) :] for n in self.notes if n.startswith(REPAIR_PREFIX)]

    @property
    def vehicle_ids(self) -> list[str]:
        return list(pd.unique(self.tracks["vehicle_id"]))

    @property
    def scene_ids(self) -> list[str]:
        return list(pd.unique(self.scenes["scene_id"]))

    @functools.cached_property
    def _vehicle_rows(self) -> dict[Any, np.ndarray]:
        # Each vehicle's row positions, found once: comparing the whole id column for every
        # vehicle asked for made a pass over all vehicles quadratic in their number.
        return self.tracks.groupby("vehicle_id", sort=False).indices

    def vehicle(self, vehicle_id: str) -> pd.DataFrame:
        """The rows of one vehicle, in time order."""
        positions = self._vehicle_rows.get(vehicle_id)
        if positions is None:
            raise KeyError(f"{self.source}: no vehicle {vehicle_id!r}")
        return self.tracks.iloc[positions]

    def scene_vehicles(self, scene_id: str) -> list[str]:
        return list(self.scenes.loc[self.scenes["scene_id"] == scene_id, "vehicle_id"])

    def subset(self, vehicle_ids) -> Trajectories:
        """The same data restricted to some vehicles (scenes and flags follow)."""
        keep = set(vehicle_ids)
        return dataclasses.replace(
            self,
            tracks=self.tracks[self.tracks["vehicle_id"].isin(keep)].reset_index(drop=True),
            scenes=self.scenes[self.scenes["vehicle_id"].isin(keep)].reset_index(drop=True),
            flags=self.flags[self.flags["vehicle_id"].isin(keep)].reset_index(drop=True),
        )

    def first_seconds(self, seconds: float) -> Trajectories:
        """The first ``seconds`` of every scene, counted from the scene's earliest sample (a
        vehicle in several scenes keeps the span of the earliest); vehicles left without a
        sample leave the scenes, flags follow."""
        if seconds <= 0:
            raise ValueError(f"the kept span must be positive, got {seconds} s")
        start_of_vehicle = self.tracks.groupby("vehicle_id")["t"].min()
        scene_start = (
            self.scenes.assign(t=self.scenes["vehicle_id"].map(start_of_vehicle))
            .groupby("scene_id")["t"]
            .min()
        )
        start = (
            self.scenes.assign(t=self.scenes["scene_id"].map(scene_start))
            .groupby("vehicle_id")["t"]
            .min()
        )
        # Vehicles outside every scene keep their own start.
        start = start.reindex(start_of_vehicle.index).fillna(start_of_vehicle)

        def kept(frame: pd.DataFrame) -> pd.Series:
            # astype: mapping an empty string column keeps its string dtype.
            return frame["t"] < frame["vehicle_id"].map(start).astype(float) + seconds

        cropped = dataclasses.replace(
            self,
            tracks=self.tracks[kept(self.tracks)].reset_index(drop=True),
            flags=self.flags[kept(self.flags)].reset_index(drop=True),
        )
        return cropped.subset(pd.unique(cropped.tracks["vehicle_id"]))

    def every(self, factor: int) -> Trajectories:
        """One sample in ``factor``: the samples at whole multiples of ``factor * dt`` on the
        time axis (one axis per scene, so leaders and followers keep the same instants), with
        ``dt`` multiplied by ``factor``. Speeds, gaps and accelerations stay as recorded at the
        kept instants. A flag at a dropped instant moves to the vehicle's next kept instant, so
        the longer step across it stays out of fitting; the change is recorded in ``notes``."""
        if int(factor) != factor or factor < 1:
            raise ValueError(f"the subsampling factor must be a whole number >= 1, got {factor}")
        factor = int(factor)
        if factor == 1:
            return self
        index = self.tracks["t"].to_numpy() / self.dt
        off_grid = np.abs(index - np.rint(index)) > 1e-6
        if off_grid.any():
            row = self.tracks[off_grid].iloc[0]
            raise ValueError(
                f"vehicle {row['vehicle_id']}: sample at t = {row['t']} s is not a whole multiple "
                f"of dt = {self.dt} s, so every {factor}-th sample is not defined"
            )
        kept = np.rint(index).astype(np.int64) % factor == 0
        tracks = self.tracks[kept].reset_index(drop=True)
        step = factor * self.dt
        # Whole steps of the new dt from 0, rounded like the kept samples' times.
        moved_t = np.ceil(np.rint(self.flags["t"].to_numpy(float) / self.dt) / factor) * step
        flags = self.flags.assign(t=moved_t)
        present = pd.MultiIndex.from_frame(tracks[["vehicle_id", "t"]].round(9))
        on_kept = pd.MultiIndex.from_frame(flags[["vehicle_id", "t"]].round(9)).isin(present)
        # A flag past a vehicle's last kept sample touches no step that is kept.
        flags = flags[on_kept].drop_duplicates(["vehicle_id", "t", "kind"]).reset_index(drop=True)
        note = (
            f"subsampled: one sample in {factor} kept (dt {self.dt:g} s -> {step:g} s); "
            f"{len(self.flags) - len(flags)} flag(s) merged or past a vehicle's last kept sample"
        )
        reduced = dataclasses.replace(
            self, tracks=tracks, flags=flags, dt=step, notes=(*self.notes, note)
        )
        return reduced.subset(pd.unique(tracks["vehicle_id"]))


def _clock_groups(scenes: pd.DataFrame) -> dict[str, int]:
    """Vehicle id -> clock group: scenes that share a vehicle share a time axis (union-find)."""
    parent: dict[str, str] = {}

    def root(node: str) -> str:
        while parent.setdefault(node, node) != node:
            parent[node] = parent[parent[node]]
            node = parent[node]
        return node

    for scene_id, vehicle_id in zip(scenes["scene_id"], scenes["vehicle_id"], strict=True):
        parent[root(f"s:{scene_id}")] = root(f"v:{vehicle_id}")
    roots = {node[2:]: root(node) for node in list(parent) if node.startswith("v:")}
    numbering = {r: i for i, r in enumerate(sorted(set(roots.values())))}
    return {vid: numbering[r] for vid, r in roots.items()}


def recorded_duration(traj: Trajectories) -> float:
    """Seconds of recording: per clock, the time covered by at least one vehicle, summed over clocks.

    Separate files often restart their clock at 0 (OpenACC recordings, merge episodes), while
    overlapping files share one (linked NGSIM chains); scenes that share a vehicle share a clock.
    Within a clock, the union of every vehicle's contiguous runs is counted once, so neither
    overlapping vehicles nor empty stretches between unrelated files inflate the figure.
    """
    tracks = traj.tracks.sort_values(["vehicle_id", "t"])
    vehicle = tracks["vehicle_id"].to_numpy()
    t = tracks["t"].to_numpy()
    new_run = np.r_[True, (np.diff(t) > 1.5 * traj.dt) | (vehicle[1:] != vehicle[:-1])]
    group_of = _clock_groups(traj.scenes)
    runs = (
        pd.DataFrame({"run": np.cumsum(new_run), "t": t, "vehicle_id": vehicle})
        .groupby("run")
        .agg(start=("t", "min"), stop=("t", "max"), vehicle_id=("vehicle_id", "first"))
    )
    runs["clock"] = runs["vehicle_id"].map(group_of).fillna(-1)
    covered = 0.0
    for _, clock_runs in runs.sort_values("start").groupby("clock"):
        end = -np.inf
        for start, stop in zip(clock_runs["start"], clock_runs["stop"], strict=True):
            covered += max(0.0, stop - max(start, end))
            end = max(end, stop)
    return float(covered)


def summary(traj: Trajectories) -> dict[str, Any]:
    """The figures ``bayesdrive data info`` reports (keys documented in the README)."""
    tracks = traj.tracks
    times = np.round(tracks["t"].to_numpy() / traj.dt).astype(np.int64)
    gaps = tracks["gap"].dropna()
    pairs = tracks.loc[tracks["leader_id"].notna(), ["vehicle_id", "leader_id"]].drop_duplicates()
    return {
        "format": traj.format,
        "source": traj.source,
        "scenes": len(traj.scene_ids),
        "vehicles": int(tracks["vehicle_id"].nunique()),
        "samples": len(tracks),
        "time_steps": len(np.unique(times)),
        "dt_s": traj.dt,
        "duration_s": recorded_duration(traj),
        "vehicle_seconds": float(len(tracks) * traj.dt),
        "leader_follower_pairs": len(pairs),
        "speed_mps": {
            "min": float(tracks["v"].min()),
            "median": float(tracks["v"].median()),
            "max": float(tracks["v"].max()),
        },
        "gap_m": {
            "min": float(gaps.min()) if len(gaps) else None,
            "median": float(gaps.median()) if len(gaps) else None,
        },
        "drivers": {k: int(n) for k, n in tracks.groupby("driver")["vehicle_id"].nunique().items()},
        "flags": {k: int(n) for k, n in traj.flags.groupby("kind").size().items()},
        "notes": list(traj.notes),
    }
