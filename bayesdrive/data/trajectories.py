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
import logging
from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from bayesdrive.data.errors import DataError

__all__ = ["FLAG_COLUMNS", "TRACK_COLUMNS", "Trajectories", "validate_tracks"]

log = logging.getLogger(__name__)

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

# A passenger car is at most ~6 m long; a median length above this in "metres" is feet.
MAX_CAR_LENGTH_M = 8.0
# A US tractor-trailer is up to ~23 m (NGSIM I-80 has 74-76 ft trucks); longer than this is feet.
MAX_VEHICLE_LENGTH_M = 30.0
# Stopped cars in a jam keep 1-4 m bumper to bumper; a median jam spacing (front to front) far above
# 15 m while speeds are below 2 m/s reads as feet passed as metres.
MAX_JAM_SPACING_M = 15.0
JAM_SPEED_MPS = 2.0


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
        notes: documented assumptions and repairs the reader made (e.g. assumed lengths).
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

    @property
    def vehicle_ids(self) -> list[str]:
        return list(pd.unique(self.tracks["vehicle_id"]))

    @property
    def scene_ids(self) -> list[str]:
        return list(pd.unique(self.scenes["scene_id"]))

    def vehicle(self, vehicle_id: str) -> pd.DataFrame:
        """The rows of one vehicle, in time order."""
        rows = self.tracks[self.tracks["vehicle_id"] == vehicle_id]
        if rows.empty:
            raise KeyError(f"{self.source}: no vehicle {vehicle_id!r}")
        return rows

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


def _where(source: str, frame: pd.DataFrame, index, column: str) -> str:
    """'file, row R, column C' for an error message; rows carry their source row when known.

    A ``_file`` column, if present, names each row's own file (readers that merge several files
    into one table set it), so the message names the file the row came from.
    """
    row = frame.loc[index, "_row"] if "_row" in frame.columns else index
    if "_file" in frame.columns and isinstance(frame.loc[index, "_file"], str):
        source = frame.loc[index, "_file"]
    return f"{source}, row {row}, column {column!r}"


def validate_tracks(
    tracks: pd.DataFrame,
    *,
    source: str,
    dt: float,
    column_names: Mapping[str, str] | None = None,
) -> pd.DataFrame:
    """Check a tracks table against the schema and return it typed and sorted.

    ``column_names`` maps schema columns to the source's own column names, so that errors name the
    column the user sees in the file. A ``_row`` column, if present, gives the source row numbers
    for messages, and a ``_file`` column the file each row came from; both are dropped from the
    result. Raises :class:`DataError` naming file, row and
    column for: missing columns, NaN in required columns, duplicate frames, time going backwards,
    an empty table, negative speeds or lengths, a leader id that names no vehicle, a time step
    that is not a multiple of ``dt``, and lengths or jam spacings that can only be feet.
    """
    names = dict(column_names or {})

    def shown(column: str) -> str:
        return names.get(column, column)

    if len(tracks) == 0:
        raise DataError(f"{source}: no data rows (empty file or nothing left after the header)")
    missing = [c for c in TRACK_COLUMNS if c not in tracks.columns]
    if missing:
        raise DataError(f"{source}: missing column(s) {', '.join(shown(c) for c in missing)}")
    if not (np.isfinite(dt) and dt > 0):
        raise DataError(f"{source}: sampling interval must be positive, got {dt!r}")

    for column in ("t", "x", "v", "length"):
        bad = tracks[column].isna() | ~np.isfinite(tracks[column].astype(float))
        if bad.any():
            first = bad.idxmax()
            raise DataError(
                f"{_where(source, tracks, first, shown(column))}: value is NaN or infinite "
                f"({int(bad.sum())} such row(s) in all)"
            )
    for column, what in (("v", "speed"), ("length", "vehicle length")):
        bad = tracks[column] < 0 if column == "v" else tracks[column] <= 0
        if bad.any():
            first = bad.idxmax()
            raise DataError(
                f"{_where(source, tracks, first, shown(column))}: negative {what} "
                f"{tracks.loc[first, column]!r}"
            )
    unknown_drivers = ~tracks["driver"].isin(DRIVERS)
    if unknown_drivers.any():
        first = unknown_drivers.idxmax()
        raise DataError(
            f"{_where(source, tracks, first, shown('driver'))}: driver must be one of {DRIVERS}, "
            f"got {tracks.loc[first, 'driver']!r}"
        )

    ordered = tracks.reset_index(drop=True)
    by_vehicle = ordered.groupby("vehicle_id", sort=False)["t"]
    step = by_vehicle.diff()
    duplicate = step == 0
    if duplicate.any():
        first = duplicate.idxmax()
        raise DataError(
            f"{_where(source, ordered, first, shown('t'))}: duplicate frame for vehicle "
            f"{ordered.loc[first, 'vehicle_id']} at t={ordered.loc[first, 't']}"
        )
    backwards = step < 0
    if backwards.any():
        first = backwards.idxmax()
        raise DataError(
            f"{_where(source, ordered, first, shown('t'))}: time goes backwards for vehicle "
            f"{ordered.loc[first, 'vehicle_id']} ({ordered.loc[first - 1, 't']} then "
            f"{ordered.loc[first, 't']})"
        )
    ratio = step / dt
    off_grid = step.notna() & (np.abs(ratio - np.round(ratio)) > 1e-3)
    if off_grid.any():
        first = off_grid.idxmax()
        raise DataError(
            f"{_where(source, ordered, first, shown('t'))}: time step {step[first]:.6g} s is not "
            f"a multiple of the sampling interval {dt} s"
        )

    known = set(ordered["vehicle_id"])
    leaders = ordered["leader_id"]
    dangling = leaders.notna() & ~leaders.isin(known)
    if dangling.any():
        first = dangling.idxmax()
        raise DataError(
            f"{_where(source, ordered, first, shown('leader_id'))}: leader id "
            f"{ordered.loc[first, 'leader_id']!r} names no vehicle in the data"
        )
    no_gap = leaders.notna() & ordered["gap"].isna()
    if no_gap.any():
        first = no_gap.idxmax()
        raise DataError(
            f"{_where(source, ordered, first, shown('gap'))}: vehicle has a leader but no gap"
        )

    _refuse_feet(ordered, source=source, shown=shown)

    typed = ordered.drop(columns=[c for c in ordered.columns if c not in TRACK_COLUMNS])
    typed = typed.astype(TRACK_COLUMNS)
    typed["leader_id"] = typed["leader_id"].where(typed["leader_id"].notna(), None)
    return typed.sort_values(["vehicle_id", "t"], kind="stable").reset_index(drop=True)


def _refuse_feet(tracks: pd.DataFrame, *, source: str, shown) -> None:
    """Refuse data whose lengths or jam spacings can only be feet read as metres.

    Congested speeds in ft/s (10-30) still look like plausible m/s, so speed alone cannot tell;
    vehicle length and the spacing of stopped cars can.
    """
    too_long = tracks["length"] > MAX_VEHICLE_LENGTH_M
    median_length = float(tracks["length"].median())
    if median_length > MAX_CAR_LENGTH_M or too_long.any():
        first = too_long.idxmax() if too_long.any() else tracks.index[0]
        raise DataError(
            f"{_where(source, tracks, first, shown('length'))}: vehicle lengths (median "
            f"{median_length:.1f}) are too long to be metres; are these feet? "
            "Pass the unit explicitly (e.g. --units ft)"
        )
    jammed = tracks["leader_id"].notna() & (tracks["v"] < JAM_SPEED_MPS)
    if jammed.sum() >= 10:
        spacing = (tracks.loc[jammed, "gap"] + tracks.loc[jammed, "length"]).median()
        if spacing > MAX_JAM_SPACING_M:
            first = jammed.idxmax()
            raise DataError(
                f"{_where(source, tracks, first, shown('gap'))}: stopped vehicles keep a median "
                f"spacing of {spacing:.1f}, too long for metres; are these feet? "
                "Pass the unit explicitly (e.g. --units ft)"
            )


def empty_flags() -> pd.DataFrame:
    return pd.DataFrame(
        {c: pd.Series(dtype="object" if c != "t" else "float64") for c in FLAG_COLUMNS}
    )


def flag_negative_gaps(tracks: pd.DataFrame) -> pd.DataFrame:
    """Flag samples whose bumper gap is not positive: physically impossible, so never fitted."""
    bad = tracks["gap"].notna() & (tracks["gap"] <= 0)
    flagged = tracks.loc[bad, ["vehicle_id", "t", "gap", "leader_id"]]
    if flagged.empty:
        return empty_flags()
    # A note, not a warning: the flags travel with the data and every summary counts them.
    log.info("%d sample(s) with a non-positive bumper gap flagged", len(flagged))
    return pd.DataFrame(
        {
            "vehicle_id": flagged["vehicle_id"].to_numpy(),
            "t": flagged["t"].to_numpy(),
            "kind": "negative_gap",
            "message": [
                f"bumper gap {g:.2f} m to leader {lead}"
                for g, lead in zip(flagged["gap"], flagged["leader_id"], strict=True)
            ],
        }
    )


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
