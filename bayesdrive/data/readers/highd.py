"""highD drone recordings (``XX_tracks.csv``, ``XX_tracksMeta.csv``, ``XX_recordingMeta.csv``).

Units (:data:`UNITS`): m, m/s, m/s^2; frame rate from ``XX_recordingMeta.csv`` (``frameRate``,
25 Hz in highD). highD recordings may not be redistributed: users bring their own files.

The format's conventions and what the reader makes of them:

- ``x``, ``y`` are the UPPER-LEFT corner of the bounding box in image-aligned metres, so ``x`` is
  the box's left edge whatever the driving direction; ``width`` is the box extent along x, i.e.
  the vehicle LENGTH (``height`` is its width).
- ``drivingDirection`` (tracksMeta): 1 = leftwards (x decreasing, upper carriageway),
  2 = rightwards (x increasing). Longitudinal position in the driving direction of the FRONT
  bumper: direction 2 -> ``x + width``; direction 1 -> the front is the left edge, so the schema's
  ``x`` (increasing in driving direction) is ``-x``.
- Speed and acceleration: ``xVelocity``/``xAcceleration`` are signed along image x; multiplied by
  +1 (direction 2) or -1 (direction 1).
- Leader: ``precedingId`` per frame (0 = none); it must be in the recording at that frame and drive
  the same direction.
- Gap: computed from positions, ``front_leader - length_leader - front`` (bumper to bumper), not
  taken from ``dhw``: the published field list only calls ``dhw`` "distance headway". The notes
  report how ``dhw`` compares with the computed bumper gap and with the front-to-front spacing.
- ``t = frame / frameRate``; ``lane_id = laneId``; one scene per recording (scene id ``XX``);
  vehicle ids ``"XX:<id>"``; ``driver`` unknown.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import pandas as pd

from bayesdrive.data.errors import DataError
from bayesdrive.data.readers._common import (
    FileFormat,
    Notes,
    finish_parts,
    gaps_from_positions,
    integer_column,
    integer_ids,
    leader_values,
    make_tracks,
    read_checked_table,
    require_regular_file,
    time_steps,
)
from bayesdrive.data.trajectories import Trajectories

__all__ = ["TRACK_COLUMNS", "UNITS", "read_highd"]

log = logging.getLogger(__name__)

FORMAT = "highd"
UNITS = {
    "x/y/width/height/dhw": "m",
    "xVelocity": "m/s",
    "xAcceleration": "m/s^2",
    "frame": "1/frameRate s",
}
TRACK_COLUMNS = [
    "frame",
    "id",
    "x",
    "y",
    "width",
    "height",
    "xVelocity",
    "xAcceleration",
    "precedingId",
    "laneId",
]
META_COLUMNS = ["id", "width", "drivingDirection"]
RECORDING_COLUMNS = ["frameRate"]
SCHEMA_NAMES = {
    "vehicle_id": "id",
    "t": "frame",
    "x": "x",
    "v": "xVelocity",
    "a": "xAcceleration",
    "lane_id": "laneId",
    "leader_id": "precedingId",
    "gap": "x/width (computed)",
    "length": "width",
}


def read_highd(path: str | Path) -> Trajectories:
    """Read one recording (its ``XX_tracks.csv``) or every recording in a folder."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    if not path.is_dir():
        require_regular_file(path)
        match = re.fullmatch(r"(.+)_tracks\.csv", path.name)
        if not match:
            raise DataError(f"{path}: a highD track file is named XX_tracks.csv")
        recordings = [(path.parent, match.group(1))]
    else:
        recordings = [
            (path, m.group(1))
            for f in sorted(path.glob("*_tracks.csv"))
            if f.is_file() and (m := re.fullmatch(r"(.+)_tracks\.csv", f.name))
        ]
        if not recordings:
            raise DataError(f"{path}: no highD recordings (XX_tracks.csv) in this folder")
    notes = Notes(log)
    notes.assume(
        "highD: x = front bumper along the driving direction (x + width for direction 2, -x for "
        "direction 1); length = bounding-box width; gap computed from positions"
    )
    parts = [_read_recording(folder, prefix, notes) for folder, prefix in recordings]
    rates = {dt for _, _, dt in parts}
    if len(rates) > 1:
        raise DataError(f"{path}: recordings have different frame rates ({sorted(rates)})")
    return finish_parts(
        parts,
        FileFormat(FORMAT, rates.pop(), SCHEMA_NAMES),
        path,
        notes,
        extra_inputs=[p for folder, prefix in recordings for p in _companions(folder, prefix)],
    )


def _companions(folder: Path, prefix: str) -> tuple[Path, Path]:
    return folder / f"{prefix}_tracksMeta.csv", folder / f"{prefix}_recordingMeta.csv"


def _read_recording(folder: Path, prefix: str, notes: Notes):
    tracks_path = folder / f"{prefix}_tracks.csv"
    meta_path, recording_path = _companions(folder, prefix)
    for needed in (meta_path, recording_path):
        if not needed.exists():
            raise DataError(f"{tracks_path}: its companion file {needed.name} is missing")

    recording = read_checked_table(
        recording_path, RECORDING_COLUMNS, fmt="highD recordingMeta", notes=notes
    )
    rate = float(recording["frameRate"].iloc[0])
    if rate <= 0:
        raise DataError(f"{recording_path}, row 2, column 'frameRate': must be positive")
    dt = 1.0 / rate

    meta = read_checked_table(
        meta_path,
        META_COLUMNS,
        [c for c in META_COLUMNS if c != "id"],
        fmt="highD tracksMeta",
        notes=notes,
        text_columns=["id"],
    )
    bad = ~meta["drivingDirection"].isin([1, 2])
    if bad.any():
        row = meta["_row"].iloc[int(np.argmax(bad.to_numpy()))]
        raise DataError(f"{meta_path}, row {row}, column 'drivingDirection': must be 1 or 2")
    direction_of = dict(zip(integer_ids(meta, "id"), meta["drivingDirection"], strict=True))

    ids = ["id", "precedingId"]
    frame = read_checked_table(
        tracks_path,
        TRACK_COLUMNS,
        [c for c in TRACK_COLUMNS if c not in ids],
        fmt="highD tracks",
        notes=notes,
        text_columns=ids,
    )
    ids = pd.Series(integer_ids(frame, "id"))
    direction = ids.map(direction_of)
    unknown = direction.isna().to_numpy()
    if unknown.any():
        first = int(np.argmax(unknown))
        raise DataError(
            f"{tracks_path}, row {frame['_row'].iloc[first]}, column 'id': vehicle "
            f"{ids.iloc[first]} is not in {meta_path.name}"
        )
    sign = np.where(direction.to_numpy() == 2, 1.0, -1.0)
    length = frame["width"].to_numpy()
    left_edge = frame["x"].to_numpy()
    front = np.where(sign > 0, left_edge + length, -left_edge)

    preceding = pd.Series(integer_ids(frame, "precedingId"))
    has_leader = (preceding != "0").to_numpy()
    leader_direction = preceding.map(direction_of).to_numpy()
    crossing = has_leader & (leader_direction != direction.to_numpy())
    if crossing.any():
        first = int(np.argmax(crossing))
        raise DataError(
            f"{tracks_path}, row {frame['_row'].iloc[first]}, column 'precedingId': leader "
            f"{preceding.iloc[first]} is unknown or drives the other direction"
        )

    def vid(values: pd.Series) -> pd.Series:
        return prefix + ":" + values.astype(str)

    leader = vid(preceding).where(has_leader, None)
    frames = integer_column(frame, "frame")
    tracks = make_tracks(
        vehicle_id=vid(ids).to_numpy(),
        t=time_steps(frames, dt),
        x=front,
        v=sign * frame["xVelocity"].to_numpy(),
        a=sign * frame["xAcceleration"].to_numpy(),
        lane_id=integer_column(frame, "laneId"),
        leader_id=leader.to_numpy(),
        length=length,
        row=frame["_row"].to_numpy(),
        file=str(tracks_path),
    )
    tracks["gap"] = gaps_from_positions(tracks, dt)
    absent = tracks["leader_id"].notna() & tracks["gap"].isna()
    if absent.any():
        first = int(np.argmax(absent.to_numpy()))
        raise DataError(
            f"{tracks_path}, row {frame['_row'].iloc[first]}, column 'precedingId': leader "
            f"{preceding.iloc[first]} has no row at frame {frames[first]}"
        )
    if "dhw" in frame.columns:
        _compare_dhw(frame, tracks, has_leader, dt, notes, tracks_path.name)
    scenes = pd.DataFrame({"scene_id": prefix, "vehicle_id": pd.unique(tracks["vehicle_id"])})
    return tracks, scenes, dt


def _compare_dhw(
    frame: pd.DataFrame,
    tracks: pd.DataFrame,
    has_leader: np.ndarray,
    dt: float,
    notes: Notes,
    name: str,
) -> None:
    dhw = pd.to_numeric(frame["dhw"], errors="coerce").to_numpy()
    usable = has_leader & np.isfinite(dhw)
    if not usable.any():
        return
    gap = tracks["gap"].to_numpy()[usable]
    spacing = gap + leader_values(tracks, "length", dt).to_numpy()[usable]  # front to front
    to_gap = np.median(np.abs(dhw[usable] - gap))
    to_spacing = np.median(np.abs(dhw[usable] - spacing))
    notes.assume(
        f"{name}: dhw vs computed gaps: median |dhw - bumper gap| = {to_gap:.2f} m, "
        f"median |dhw - front-to-front spacing| = {to_spacing:.2f} m (gap from positions used)"
    )
