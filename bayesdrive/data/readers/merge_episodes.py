"""NGSIM on-ramp merge episodes (``ngsim_merge_episodes``): ego-centric relative states.

Units (:data:`UNITS`): m, m/s, m/s^2, 10 Hz. Per row: the merging car's (ego's) speed,
acceleration and distance to the end of the acceleration lane, then distance ``d_Vi`` and relative
speed ``dv_Vi`` of up to five neighbours V1..V5 (``d_Vi = x_Vi - x_ego``, ``dv_Vi = v_Vi - v_ego``),
then the action (not part of the trajectory schema: ignored). ``d = 100, dv = 30`` is the
sentinel for a missing neighbour: those samples are absent, not values.

Representation, one scene per episode (scene id ``ep<n>``):

- ego ``ep<n>_ego``: ``x = -dist_to_end`` (the merge point, the end of the acceleration lane, is
  x = 0), ``v``, ``a`` measured, lane 0 (the acceleration lane).
- neighbour ``ep<n>_V<i>``: ``x = x_ego + d_Vi``, ``v = v_ego + dv_Vi``, no acceleration.
- Lanes and leaders, INFERRED from the signs of ``d`` (V1, V2 always behind, V3-V5 ahead; the
  source's figure was not readable, see PROVENANCE): V1-V4 on the main lane (lane 1) in the order
  V1, V2, V3, V4 from back to front, so V1 follows V2, V2 follows V3, V3 follows V4; V5 leads the
  ego on the acceleration lane (lane 0).
- Gap: ``x_leader - x - length`` with every car assumed :data:`ASSUMED_LENGTH_M` long.
- No vehicle ids in the source: a slot whose distance jumps by more than :data:`SLOT_JUMP_M`
  between consecutive steps holds a different car afterwards, and a slot that reappears after the
  sentinel may too; both start a new vehicle (``ep3_V2_b``, ``ep3_V2_c``, ...) instead of dropping
  data. Counts in the notes.

``dataset_with_episode_ids.csv`` (with ``episode`` and ``t_s``) is preferred; the published
``dataset.npy`` (4877 x 14, no header) is read too, its episodes found where the distance to the
lane end jumps up and its time counted from 0 in steps of 0.1 s.
"""

from __future__ import annotations

import logging
import string
from pathlib import Path

import numpy as np
import pandas as pd

from bayesdrive.data.errors import DataError
from bayesdrive.data.readers._common import (
    Notes,
    finish,
    gaps_from_positions,
    integer_column,
    make_tracks,
    numeric_columns,
    read_checked_table,
    require_regular_file,
    snap_to_grid,
    sort_rows,
    time_steps,
)
from bayesdrive.data.trajectories import Trajectories

__all__ = ["ASSUMED_LENGTH_M", "DT", "SLOT_JUMP_M", "UNITS", "read_merge_episodes"]

log = logging.getLogger(__name__)

FORMAT = "merge_episodes"
DT = 0.1
UNITS = {"ego_v": "m/s", "ego_a": "m/s^2", "dist_to_end": "m", "d_Vi": "m", "dv_Vi": "m/s"}
ASSUMED_LENGTH_M = 4.5
SENTINEL_D, SENTINEL_DV = 100.0, 30.0
SLOT_JUMP_M = 5.0
SLOTS = (1, 2, 3, 4, 5)
LANE = {"ego": 0, 1: 1, 2: 1, 3: 1, 4: 1, 5: 0}
# Who follows whom (follower slot -> leader slot); "ego" is the merging car.
LEADER_SLOT = {1: 2, 2: 3, 3: 4, "ego": 5}
NPY_COLUMNS = [
    "ego_v_mps",
    "ego_a_mps2",
    "ego_dist_to_accel_lane_end_m",
    *[f"{p}_V{i}_{u}" for i in SLOTS for p, u in (("d", "m"), ("dv", "mps"))],
    "action",
]
CSV_COLUMNS = ["episode", "t_s", *NPY_COLUMNS[:-1]]
CSV_NAME = "dataset_with_episode_ids.csv"
NPY_NAME = "dataset.npy"


def read_merge_episodes(path: str | Path, *, length: float = ASSUMED_LENGTH_M) -> Trajectories:
    """Read the merge-episode CSV (or ``dataset.npy``, or the folder holding them)."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    if path.is_dir():
        if (path / CSV_NAME).exists():
            path = path / CSV_NAME
        elif (path / NPY_NAME).exists():
            path = path / NPY_NAME
        else:
            raise DataError(f"{path}: neither {CSV_NAME} nor {NPY_NAME} in this folder")
    notes = Notes(log)
    frame = _read_npy(path, notes) if path.suffix == ".npy" else _read_csv(path, notes)

    notes.assume(
        "merge episodes: ego x = -distance to the end of the acceleration lane (merge point at "
        "x = 0), neighbour x = x_ego + d, v = v_ego + dv; lanes and leaders INFERRED from the "
        "signs of d: V1..V4 main lane (lane 1) back to front, V1->V2->V3->V4 car-following; V5 "
        "leads the ego on the acceleration lane (lane 0); action column ignored"
    )
    notes.assume(f"no vehicle lengths: every car assumed {length} m long")

    steps = snap_to_grid(frame["t_s"], DT, frame, column="t_s")
    episode = integer_column(frame, "episode")
    x_ego = -frame["ego_dist_to_accel_lane_end_m"].to_numpy()
    v_ego = frame["ego_v_mps"].to_numpy()
    same_episode = np.r_[False, episode[1:] == episode[:-1]]

    ids: dict[object, np.ndarray] = {"ego": np.array([f"ep{e}_ego" for e in episode], dtype=object)}
    present: dict[object, np.ndarray] = {"ego": np.ones(len(frame), dtype=bool)}
    positions: dict[object, np.ndarray] = {"ego": x_ego}
    jumps = reappearances = 0
    for i in SLOTS:
        d = frame[f"d_V{i}_m"].to_numpy()
        dv = frame[f"dv_V{i}_mps"].to_numpy()
        here = ~((d == SENTINEL_D) & (dv == SENTINEL_DV))
        previous_here = np.r_[False, here[:-1]] & same_episode
        jump = here & previous_here & (np.abs(np.diff(d, prepend=d[0])) > SLOT_JUMP_M)
        back = here & ~previous_here & same_episode & _seen_before(here, episode)
        jumps += int(jump.sum())
        reappearances += int(back.sum())
        # Segment number within (episode, slot): increases at each jump or reappearance.
        new_car = (jump | back).astype(np.int64)
        segment = pd.Series(new_car).groupby(episode).cumsum().to_numpy()
        ids[i] = np.array(
            [f"ep{e}_V{i}{_suffix(s)}" for e, s in zip(episode, segment, strict=True)], dtype=object
        )
        present[i] = here
        positions[i] = x_ego + d
    if jumps:
        notes.assume(
            f"{jumps} slot re-assignment(s) (|delta d| > {SLOT_JUMP_M} m between steps): the car "
            "after the jump gets a new id (suffix _b, _c, ...); no data dropped",
            warn=True,
        )
    if reappearances:
        notes.assume(
            f"{reappearances} slot(s) reappear after the missing-neighbour sentinel: treated as a "
            "new car (new id suffix), since no vehicle ids say otherwise",
            warn=True,
        )
    sentinel_samples = sum(int((~present[i]).sum()) for i in SLOTS)
    notes.assume(
        f"{sentinel_samples} neighbour samples carry the sentinel d={SENTINEL_D:g}, "
        f"dv={SENTINEL_DV:g} (neighbour absent): left out, not values"
    )

    parts = []
    rows = frame["_row"].to_numpy()
    t = time_steps(steps, DT)
    for slot in ("ego", *SLOTS):
        mask = present[slot]
        leader_slot = LEADER_SLOT.get(slot)
        leader = np.full(len(frame), None, dtype=object)
        if leader_slot is not None:
            has = present[leader_slot]
            leader[has] = ids[leader_slot][has]
        if slot == "ego":
            v = v_ego
            a = frame["ego_a_mps2"].to_numpy()
        else:
            v = v_ego + frame[f"dv_V{slot}_mps"].to_numpy()
            a = np.full(len(frame), np.nan)
        parts.append(
            make_tracks(
                vehicle_id=ids[slot][mask],
                t=t[mask],
                x=positions[slot][mask],
                v=v[mask],
                a=a[mask],
                lane_id=LANE[slot],
                leader_id=leader[mask],
                length=float(length),
                row=rows[mask],
                file=str(path),
            )
        )
    tracks = pd.concat(parts, ignore_index=True)
    tracks["gap"] = gaps_from_positions(tracks, DT)
    scenes = pd.DataFrame(
        {
            "scene_id": tracks["vehicle_id"].str.split("_").str[0],
            "vehicle_id": tracks["vehicle_id"],
        }
    ).drop_duplicates()
    names = {
        "x": "ego_dist_to_accel_lane_end_m / d_Vi_m",
        "v": "ego_v_mps / dv_Vi_mps",
        "t": "t_s",
    }
    return finish(
        tracks, fmt=FORMAT, source=path, dt=DT, scenes=scenes, notes=notes, column_names=names
    )


def _suffix(segment: int) -> str:
    if segment == 0:
        return ""
    if segment < 26:
        return "_" + string.ascii_lowercase[segment]
    return f"_{segment + 1}"


def _seen_before(here: np.ndarray, episode: np.ndarray) -> np.ndarray:
    """True where the slot was present at some earlier step of the same episode."""
    earlier = pd.Series(here.astype(int)).groupby(episode).cumsum().to_numpy() - here
    return earlier > 0


def _read_csv(path: Path, notes: Notes) -> pd.DataFrame:
    frame = read_checked_table(path, CSV_COLUMNS, fmt="merge-episode", notes=notes)
    return sort_rows(frame, ["episode", "t_s"], notes=notes, path=path, what="episode and time")


def _read_npy(path: Path, notes: Notes) -> pd.DataFrame:
    require_regular_file(path)
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: cannot read as a numpy array ({exc})") from None
    if array.ndim != 2 or array.shape[1] != len(NPY_COLUMNS):
        raise DataError(
            f"{path}: expected a (rows, {len(NPY_COLUMNS)}) array with columns "
            f"{', '.join(NPY_COLUMNS)}; got shape {array.shape}"
        )
    if len(array) == 0:
        raise DataError(f"{path}: no data rows")
    frame = pd.DataFrame(array, columns=NPY_COLUMNS)
    frame["_row"] = np.arange(len(frame))  # 0-based array index: there is no header line
    frame["_file"] = str(path)
    numeric_columns(frame, NPY_COLUMNS)
    dist = frame["ego_dist_to_accel_lane_end_m"].to_numpy()
    episode = np.r_[0, np.cumsum(np.diff(dist) > 0)]
    frame["episode"] = episode
    frame["t_s"] = pd.Series(np.ones(len(frame))).groupby(episode).cumsum().to_numpy() - 1
    frame["t_s"] *= DT
    notes.assume(
        f"{path.name}: no episode ids; {episode[-1] + 1} episodes start where the distance to the "
        "lane end jumps up; t counted from 0 per episode; rows named by 0-based array index"
    )
    return frame
